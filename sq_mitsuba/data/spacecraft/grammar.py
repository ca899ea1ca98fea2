"""Attachment grammar of the compositional generator: host bodies, mount sites, appendages.

A spacecraft is composed, not drawn from a template: hosts (:class:`Body`: box and prism
buses, modules, nodes, blocks at the tips of booms) offer mount *sites* (:class:`Site`: a
point on the surface, its outward normal, and how deep the host is behind it), and the rules
below attach appendages to sites in any direction, not only along the host's axes:

* :func:`mount` places a part list built in its own frame (mounting point at the origin,
  main axis ``along``) at a site, pointing in any ``direction``, its second axis turned
  towards ``up`` (the sun, for arrays);
* :func:`wing` builds an array of one of :data:`WING_STYLES` along +x, cells facing +z;
* :func:`boom_from` grows a boom (or mast, arm, truss) from a site and returns the site at
  its tip, where :func:`tip_block` puts a host for the next appendage (dish, RTG, sensor,
  instrument platform), so appendages chain: bus -> boom -> block -> dish;
* :func:`dish` builds a dish on its mast along +z.

Attachment convention (as in :mod:`sq_mitsuba.data.spacecraft.parts`): every appendage
reaches ``embed`` behind its mounting point, inside its host, so the two overlap by a
positive volume and the exact union is one piece; :meth:`Site.embed` gives a safe depth.
Rods (booms, masts, struts) are at least :func:`rod_radius` thick, so after the model is
scaled to unit size no rod is thinner than a solar panel.

Randomness: the helpers that take ``rng`` draw a fixed number of values in a fixed order.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from sq_mitsuba.data.spacecraft import parts as P
from sq_mitsuba.data.spacecraft.parts import Part, place, rotation_about

X = np.array([1.0, 0.0, 0.0])
Y = np.array([0.0, 1.0, 0.0])
Z = np.array([0.0, 0.0, 1.0])
MLI = ("gold_mli", "silver_mli")
BUS_MATERIALS = ("gold_mli", "silver_mli", "gold_mli", "white_paint", "aluminium")
WING_STYLES = ("rect", "double", "cross", "circular", "rollout", "gull")
"""Array styles: rectangular panels; two blankets on a central mast (ISS-, Hubble-like);
a cross of panels (Psyche-like); a round UltraFlex disc; a roll-out blanket between two
edge booms (ROSA); panels with a folded outer section (gull wing, MAVEN-like)."""


def pick(rng: np.random.Generator, options: Sequence, p: Sequence[float] | None = None):
    """One of ``options`` (one draw)."""
    if p is None:
        return options[int(rng.integers(len(options)))]
    return options[int(rng.choice(len(options), p=np.asarray(p, float) / np.sum(p)))]


def chance(rng: np.random.Generator, probability: float) -> bool:
    """True with ``probability`` (one draw)."""
    return bool(rng.random() < probability)


def unit(v: Sequence[float]) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def perpendicular(v: Sequence[float]) -> np.ndarray:
    """A unit vector perpendicular to ``v`` (deterministic)."""
    v = unit(v)
    helper = X if abs(v[0]) < 0.9 else Y
    return unit(np.cross(v, helper))


def orient(a_local: Sequence[float], a_world: Sequence[float],
           b_local: Sequence[float] | None = None, b_world: Sequence[float] | None = None,
           ) -> np.ndarray:
    """The rotation taking ``a_local`` to ``a_world`` and turning ``b_local`` (perpendicular
    to ``a_local``) as close as it goes to ``b_world``; without ``b`` the shortest one."""
    a_local, a_world = unit(a_local), unit(a_world)
    if b_local is None or b_world is None:
        c = float(a_local @ a_world)
        if c > 1 - 1e-12:
            return np.eye(3)
        if c < -1 + 1e-12:
            return rotation_about(perpendicular(a_local), 180)
        return rotation_about(np.cross(a_local, a_world), np.degrees(np.arccos(c)))

    def frame(a: np.ndarray, b: Sequence[float]) -> np.ndarray:
        b = np.asarray(b, float) - (np.asarray(b, float) @ a) * a
        b = perpendicular(a) if np.linalg.norm(b) < 1e-9 else unit(b)
        return np.column_stack([a, b, np.cross(a, b)])

    return frame(a_world, b_world) @ frame(a_local, b_local).T


def tilted(rng: np.random.Generator, axis: Sequence[float], max_deg: float,
           min_deg: float = 0.0) -> np.ndarray:
    """``axis`` tilted by an angle in [min_deg, max_deg] towards a random side (two draws)."""
    angle = np.radians(rng.uniform(min_deg, max_deg))
    azimuth = rng.uniform(0.0, 360.0)
    axis = unit(axis)
    side = rotation_about(axis, azimuth) @ perpendicular(axis)
    return unit(np.cos(angle) * axis + np.sin(angle) * side)


def turned(axis: Sequence[float], toward: Sequence[float], degrees: float) -> np.ndarray:
    """``axis`` turned by ``degrees`` towards ``toward`` (in the plane of the two)."""
    axis = unit(axis)
    t = np.asarray(toward, float) - (np.asarray(toward, float) @ axis) * axis
    t = perpendicular(axis) if np.linalg.norm(t) < 1e-9 else unit(t)
    a = np.radians(degrees)
    return unit(np.cos(a) * axis + np.sin(a) * t)


def rod_radius(radius: float, thin: float) -> float:
    """A rod's radius, at least 0.6 ``thin``: no rod thinner than a panel at unit size."""
    return max(float(radius), 0.6 * float(thin))


# ------------------------------------------------------------------------------ sites

@dataclass(frozen=True)
class Site:
    """A mount site: a point on a host's surface, its outward normal, and ``depth``, how far
    the host's solid reaches behind the point (along -normal) at the least."""

    point: np.ndarray
    normal: np.ndarray
    depth: float

    def embed(self, cap: float | None = None) -> float:
        """How far an appendage may reach behind the point: half the depth (or ``cap``)."""
        e = 0.5 * self.depth
        return e if cap is None else min(e, cap)

    def offset(self, vector: Sequence[float]) -> Site:
        """The site moved by ``vector`` (along the surface, for a flat face)."""
        return Site(self.point + np.asarray(vector, float), self.normal, self.depth)


@dataclass
class Body:
    """A host solid with mount sites: a box (``half`` = half sizes) or a regular prism along
    its local z (``half`` = (circumradius, apothem, half height), ``sides`` faces), placed by
    ``rotation`` and ``center`` in the body frame."""

    parts: list[Part]
    shape: str
    half: np.ndarray
    sides: int = 4
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def _site(self, local_point: np.ndarray, local_normal: np.ndarray, depth: float) -> Site:
        return Site(self.rotation @ local_point + self.center, self.rotation @ unit(local_normal),
                    float(depth))

    @property
    def size(self) -> np.ndarray:
        """Side lengths along the local axes (prism: across the flats in x and y)."""
        if self.shape == "box":
            return 2 * self.half
        return np.array([2 * self.half[1], 2 * self.half[1], 2 * self.half[2]])

    def axis(self, local: Sequence[float]) -> np.ndarray:
        """A local direction in the body frame."""
        return self.rotation @ unit(local)

    def _face_normals(self) -> np.ndarray:
        offset = 0.0 if self.sides % 2 == 0 else np.pi / self.sides
        angles = offset + 2 * np.pi * np.arange(self.sides) / self.sides
        return np.stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)], axis=1)

    def ray(self, direction: Sequence[float], origin: Sequence[float] = (0.0, 0.0, 0.0),
            ) -> Site:
        """The site where a ray from the local ``origin`` (inside the body) along the local
        ``direction`` leaves the body."""
        d = unit(direction)
        o = np.asarray(origin, float)
        if self.shape == "box":
            with np.errstate(divide="ignore", invalid="ignore"):
                t_axis = np.where(np.abs(d) > 1e-12, (self.half - np.sign(d) * o) / np.abs(d),
                                  np.inf)
            k = int(np.argmin(t_axis))
            normal = np.zeros(3)
            normal[k] = np.sign(d[k])
            return self._site(o + t_axis[k] * d, normal, self.half[k])
        normals = self._face_normals()
        cos = normals @ d
        with np.errstate(divide="ignore", invalid="ignore"):
            t_faces = np.where(cos > 1e-12, (self.half[1] - normals @ o) / cos, np.inf)
        k = int(np.argmin(t_faces))
        t_cap = (self.half[2] - np.sign(d[2]) * o[2]) / abs(d[2]) if abs(
            d[2]) > 1e-12 else np.inf
        if t_faces[k] <= t_cap:
            return self._site(o + t_faces[k] * d, normals[k], self.half[1])
        return self._site(o + t_cap * d, np.array([0, 0, np.sign(d[2])]), self.half[2])

    def toward(self, direction: Sequence[float], shift: Sequence[float] = (0.0, 0.0, 0.0),
               ) -> Site:
        """:meth:`ray` in the body frame: from the centre moved by ``shift`` along
        ``direction`` (the shift is not clamped: keep it within the body's half sizes)."""
        rt = self.rotation.T
        return self.ray(rt @ unit(direction), rt @ np.asarray(shift, float))

    def face(self, name: str, u: float = 0.0, v: float = 0.0) -> Site:
        """The site at fractions ``u``, ``v`` in [-1, 1] across face ``name`` ("+x", "-z"...)
        of a box, or a cap ("+z", "-z") of a prism (fractions of 0.8 of the apothem)."""
        axis = "xyz".index(name[1])
        sign = 1.0 if name[0] == "+" else -1.0
        others = [a for a in range(3) if a != axis]
        point = np.zeros(3)
        point[axis] = sign * self.half[axis] if self.shape == "box" else sign * self.half[2]
        if self.shape == "box":
            point[others[0]] = u * self.half[others[0]] * 0.9
            point[others[1]] = v * self.half[others[1]] * 0.9
            depth = self.half[axis]
        else:
            if axis != 2:
                raise ValueError(f"face {name!r}: a prism has caps +z and -z; use side()")
            point[0], point[1] = 0.8 * self.half[1] * u, 0.8 * self.half[1] * v
            depth = self.half[2]
        normal = np.zeros(3)
        normal[axis] = sign
        return self._site(point, normal, depth)

    def side(self, azimuth_deg: float, height: float = 0.0) -> Site:
        """The site on the side wall at ``azimuth_deg`` about the local z, at ``height`` in
        [-1, 1] of the half height (box: the side faces)."""
        a = np.radians(azimuth_deg)
        h = self.half[2] * 0.9 * height
        return self.ray((np.cos(a), np.sin(a), 0.0), (0.0, 0.0, h))

    @property
    def radius(self) -> float:
        """Radius of the smallest z-axis cylinder around the body (box: its xy corners)."""
        if self.shape == "box":
            return float(np.hypot(self.half[0], self.half[1]))
        return float(self.half[0])


def box_body(size: Sequence[float], material: str, kind: str = "bus_box",
             center: Sequence[float] = (0, 0, 0), rotation: np.ndarray | None = None) -> Body:
    """A box host of ``size`` (local x, y, z)."""
    rotation = np.eye(3) if rotation is None else rotation
    parts = place([Part(kind, material, P.box(size))], rotation, center)
    return Body(parts, "box", np.asarray(size, float) / 2, 4, rotation, np.asarray(center, float))


def prism_body(sides: int, radius: float, height: float, material: str, kind: str | None = None,
               center: Sequence[float] = (0, 0, 0), rotation: np.ndarray | None = None) -> Body:
    """A regular prism host (``sides`` >= 16 is a cylinder) along its local z."""
    rotation = np.eye(3) if rotation is None else rotation
    kind = kind or {3: "bus_triangular", 6: "bus_hexagonal", 8: "bus_octagonal"}.get(
        sides, "bus_cylinder" if sides >= 16 else "bus_prism")
    parts = place([Part(kind, material, P.prism(sides, radius, height))], rotation, center)
    half = np.array([radius, radius * np.cos(np.pi / sides), height / 2])
    return Body(parts, "prism", half, sides, rotation, np.asarray(center, float))


def module_body(radius: float, length: float, material: str, center: Sequence[float],
                axis: Sequence[float]) -> Body:
    """A pressurised module (cylinder with end cones and rings) along ``axis``, centred at
    ``center``: a cylinder host reaching its docking rings (``half[2]`` is half the length).
    Mount appendages on its middle half (the cylinder); the ends are tapered."""
    rotation = orient(Z, axis)
    parts = place(P.pressurised_module(radius, length, material), rotation, center)
    return Body(parts, "prism", np.array([radius, radius * np.cos(np.pi / 32), length / 2]),
                32, rotation, np.asarray(center, float))


def stacked_on(lower: Body, upper_height: float, upper_scale: float, material: str,
               sides: int | None = None, overlap: float = 0.05) -> Body:
    """A second bus stacked on ``lower``'s +z face (a box on a box, or a prism), sunk
    ``overlap`` into it; ``upper_scale`` of the lower's size across."""
    top = lower.face("+z")
    center = top.point + (upper_height / 2 - overlap) * top.normal
    if sides is None and lower.shape == "box":
        size = np.array([lower.size[0] * upper_scale, lower.size[1] * upper_scale, upper_height])
        return box_body(size, material, "bus_box", center, lower.rotation)
    n = sides or lower.sides
    return prism_body(n, lower.half[1] * upper_scale / np.cos(np.pi / n), upper_height,
                      material, None, center, lower.rotation)


# --------------------------------------------------------------------------- placement

def mount(parts: Sequence[Part], site: Site, along: Sequence[float] = Z,
          direction: Sequence[float] | None = None, up_local: Sequence[float] | None = None,
          up: Sequence[float] | None = None, lift: float = 0.0) -> list[Part]:
    """``parts`` (mounting point at their origin, main axis ``along``) placed at ``site``:
    the main axis along ``direction`` (default: the site's normal, i.e. straight out), the
    local ``up_local`` turned towards ``up``, origin ``lift`` out along the normal."""
    d = site.normal if direction is None else unit(direction)
    rotation = orient(along, d, up_local, up)
    return place(parts, rotation, np.asarray(site.point) + lift * np.asarray(site.normal))


def box_on(site: Site, size: Sequence[float], material: str, kind: str = "instrument",
           up: Sequence[float] | None = None, sink: float | None = None,
           aperture: bool = False) -> list[Part]:
    """A box (local z along the site's normal, ``size[2]`` tall) standing on ``site``, sunk
    ``sink`` (default: a quarter of its height, at most the site's safe embed) into it."""
    sink = min(0.25 * size[2], site.embed()) if sink is None else sink
    if aperture:
        local = P.instrument_box(size, material)
    else:
        local = [Part(kind, material, P.box(size))]
    local = place(local, None, (0, 0, size[2] / 2 - sink))
    return mount(local, site, Z, None, X if up is not None else None, up)


def cylinder_on(site: Site, radius: float, height: float, material: str,
                kind: str = "instrument", sink: float | None = None, sides: int = 16,
                direction: Sequence[float] | None = None) -> list[Part]:
    """A cylinder standing on ``site`` along ``direction`` (default: its normal)."""
    sink = min(0.25 * height, site.embed()) if sink is None else sink
    local = [Part(kind, material, P.transform_solid(P.prism(sides, radius, height), None,
                                                    (0, 0, height / 2 - sink)))]
    return mount(local, site, Z, direction)


def boom_from(site: Site, direction: Sequence[float], length: float, radius: float,
              kind: str = "boom", material: str = "aluminium") -> tuple[list[Part], Site]:
    """A rod from inside the host at ``site`` out along ``direction`` for ``length``; returns
    its parts and the site at its tip (normal along the boom, depth its radius)."""
    d = unit(direction)
    root = np.asarray(site.point) - site.embed(cap=max(3 * radius, 0.1)) * d
    tip = np.asarray(site.point) + length * d
    return [Part(kind, material, P.rod(root, tip, radius))], Site(tip, d, radius)


def tip_block(tip: Site, size: float, material: str = "aluminium", kind: str = "gimbal",
              up: Sequence[float] | None = None, shape: Sequence[float] | None = None) -> Body:
    """A box host centred at a boom's ``tip`` (the boom ends inside it), its local z along
    the boom; ``shape`` (3,) scales it (default a cube of ``size``)."""
    dims = np.full(3, float(size)) if shape is None else np.asarray(shape, float)
    rotation = orient(Z, tip.normal, X if up is not None else None, up)
    center = np.asarray(tip.point) + tip.normal * (dims[2] / 2 - 1.5 * tip.depth)
    return box_body(dims, material, kind, center, rotation)


def dish(rng: np.random.Generator, diameter: float, thin: float, mast: float = 0.0,
         embed: float = 0.1, material: str = "antenna_white") -> list[Part]:
    """A parabolic dish on a mast along +z: the mast from ``embed`` behind the origin through
    ``mast`` of free length into the dish's vertex (two draws: depth, feed)."""
    depth = diameter * rng.uniform(0.1, 0.25)
    feed = chance(rng, 0.8)
    parts = place(P.parabolic_dish(diameter, depth, thin, feed=feed, material=material),
                  None, (0, 0, mast))
    radius = rod_radius(max(0.03 * diameter, thin), thin)
    parts.append(Part("antenna_mast", "aluminium",
                      P.rod((0, 0, -embed), (0, 0, mast + 0.6 * thin), radius, 12)))
    return parts


def dish_at(rng: np.random.Generator, site: Site, diameter: float, thin: float,
            facing: Sequence[float] | None = None, mast: float = 0.0,
            material: str = "antenna_white") -> list[Part]:
    """:func:`dish` at ``site``, opening towards ``facing`` (default: the site's normal)."""
    local = dish(rng, diameter, thin, mast, site.embed(cap=max(0.1, 0.1 * diameter)), material)
    return mount(local, site, Z, facing)


# ------------------------------------------------------------------------------- arrays

def wing(rng: np.random.Generator, style: str, span: float, chord: float, panels: int,
         thin: float, yoke: float = 0.3, embed: float | None = None, cant_deg: float = 0.0,
         ) -> list[Part]:
    """An array of ``style`` (see :data:`WING_STYLES`) along +x from the origin, cells facing
    +z, reaching ``embed`` behind the origin (one draw: the fold of a gull wing)."""
    fold = rng.uniform(15, 35)
    yoke_r = rod_radius(max(0.004, 0.025 * chord, 0.012 * span if style == "circular" else 0),
                        thin)
    gap = min(0.02, 0.05 * chord) if chord > 0 else 0.02
    embed = 3 * yoke_r if embed is None else embed
    panels = max(1, int(panels))
    if style == "rect":
        return P.solar_wing(span, chord, panels, thin, yoke, gap=gap, cant_deg=cant_deg,
                            yoke_radius=yoke_r, embed=embed)
    if style == "circular":
        return P.circular_wing(span / 2, thin, yoke, sides=14, yoke_radius=yoke_r, embed=embed)
    cant = rotation_about(X, cant_deg)
    if style == "double":  # two blankets either side of a central mast (ISS, Hubble)
        mast_r = rod_radius(max(0.04, 0.04 * chord), thin)
        parts = [Part("yoke", "aluminium", P.rod((-embed, 0, 0), (yoke + 0.01, 0, 0), yoke_r)),
                 Part("array_mast", "aluminium",
                      P.rod((yoke - 2 * mast_r, 0, 0), (yoke + span, 0, 0), mast_r, 8))]
        half = chord / 2
        for sign in (1, -1):
            blanket = P.box((span * 0.96, half, thin), (yoke + span / 2, sign * (half / 2 +
                                                                             mast_r * 0.5), 0))
            parts.append(Part("solar_panel", "solar_cell", P.transform_solid(blanket, cant)))
        parts.append(Part("yoke", "aluminium", P.box((2 * mast_r, chord * 1.02, 2 * mast_r),
                                                     (yoke + span, 0, 0))))
        return parts
    if style == "rollout":  # a blanket between two edge booms (ROSA)
        boom_r = rod_radius(max(0.03, 0.025 * chord), thin)
        parts = [Part("yoke", "aluminium", P.rod((-embed, 0, 0), (yoke + 0.01, 0, 0), yoke_r)),
                 Part("yoke", "aluminium", P.rod((yoke, -chord / 2, 0), (yoke, chord / 2, 0),
                                                 boom_r))]
        for sign in (1, -1):
            parts.append(Part("array_boom", "aluminium",
                              P.rod((yoke, sign * chord / 2, 0),
                                    (yoke + span, sign * chord / 2, 0), boom_r)))
        parts.append(Part("yoke", "aluminium", P.rod((yoke + span, -chord / 2, 0),
                                                     (yoke + span, chord / 2, 0), boom_r)))
        blanket = P.box((span, chord, thin), (yoke + span / 2, 0, 0))
        parts.append(Part("solar_panel", "solar_cell", P.transform_solid(blanket, cant)))
        return parts
    if style == "cross":  # a long strip with side panels at its middle (Psyche)
        parts = P.solar_wing(span, chord, panels, thin, yoke, gap=gap, cant_deg=cant_deg,
                             yoke_radius=yoke_r, embed=embed)
        mid = yoke + span * 0.5
        for sign in (1, -1):
            side = P.box((span / max(panels, 2), chord * 0.95, thin),
                         (mid, sign * chord * 0.97, 0))
            parts.append(Part("solar_panel", "solar_cell", P.transform_solid(side, cant)))
        return parts
    if style == "gull":  # inner panels flat, outer panels folded up (MAVEN)
        inner = max(1, panels // 2)
        inner_span = span * inner / panels
        parts = P.solar_wing(inner_span, chord, inner, thin, yoke, gap=gap,
                             cant_deg=cant_deg, yoke_radius=yoke_r, embed=embed)
        outer = P.solar_wing(span - inner_span, chord, max(1, panels - inner), thin, 0.02,
                             gap=gap, cant_deg=cant_deg, yoke_radius=yoke_r,
                             embed=0.1 * inner_span)
        tip = yoke + inner_span - 0.06 * inner_span
        return parts + place(outer, rotation_about(Y, -fold), (tip, 0, 0))
    raise ValueError(f"style: unknown {style!r}; choose from {WING_STYLES}")


def wing_at(site: Site, direction: Sequence[float], sun: Sequence[float], parts: list[Part],
            ) -> list[Part]:
    """A wing built by :func:`wing` mounted at ``site`` along ``direction``, its cells turned
    towards ``sun`` (as far as the wing axis allows)."""
    return mount(parts, site, X, direction, Z, sun)


def wing_pair_at(body: Body, rng: np.random.Generator, style: str, span: float, chord: float,
                 panels: int, thin: float, axis: Sequence[float], sun: Sequence[float],
                 yoke: float = 0.4, cant_deg: float = 0.0, height: float = 0.0) -> list[Part]:
    """Two wings on opposite sides of ``body`` along +-``axis`` (a local xy direction), cells
    towards ``sun`` turned by +-``cant_deg`` about each wing."""
    parts: list[Part] = []
    a = np.degrees(np.arctan2(axis[1], axis[0]))
    for k, sign in enumerate((1.0, -1.0)):
        site = body.side(a + 180 * k, height)
        local = wing(rng, style, span, chord, panels, thin, yoke,
                     embed=site.embed(cap=0.3 + 0.1 * yoke), cant_deg=sign * cant_deg)
        parts += wing_at(site, site.normal, sun, local)
    return parts


def truss_between(start: Sequence[float], end: Sequence[float], width: float, radius: float,
                  bays: int, up: Sequence[float] = Z) -> list[Part]:
    """A square lattice truss from ``start`` to ``end`` (see :func:`parts.truss`), its faces
    turned towards ``up``; put both ends inside the hosts it joins."""
    p0, p1 = np.asarray(start, float), np.asarray(end, float)
    length = float(np.linalg.norm(p1 - p0))
    local = P.truss(length, width, radius, max(1, int(bays)))
    return place(local, orient(X, p1 - p0, Z, up), p0)
