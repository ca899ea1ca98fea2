"""Geometry layer: pure torch and numpy, no renderer.

Superquadrics (primal and dual), rotations (6D, quaternion, matrix, Euler angles), rigid
poses, icospheres, assemblies of primitives (16 numbers each), the pinhole camera, and
orthonormal frames. Imports only the shared utilities (``checks``, ``io``).
"""
