"""Parts library: closed solids (manifold3d) with a kind and a material tag.

Every builder returns a list of :class:`Part` in a local frame; :func:`place` moves a list of
parts rigidly. Sizes are in metres of a notional real spacecraft; the model processing scales
everything to unit size later.

Convention: builders put their part's main axis along +z (buses, tubes, dishes opening
towards +z, nozzles pointing their exhaust towards -z), and wings extend along +x with the
cell side facing +z. Every solid is closed and outward oriented, so the union of a
spacecraft's parts is exact (:mod:`sq_mitsuba.data.spacecraft.generator`).

Attachment convention: a real spacecraft is one connected body, so every appendage builder
that mounts on a surface at its origin (wings, booms, masts, horns, nozzles, star trackers)
reaches ``embed`` (or a fixed fraction of its own size) *behind* the origin, into the
mounting surface. Placed with its origin on a bus face, the part then overlaps the bus by a
positive volume and the exact union merges the two into one piece (parts that merely touch
along a face, an edge or a point do not reliably merge).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import manifold3d
import numpy as np

from sq_mitsuba.render.materials import material_index

Solid = manifold3d.Manifold

CIRCLE_SEGMENTS = 32  # facets of "round" parts: smooth enough at 256 px, cheap to union


@dataclass(frozen=True)
class Part:
    """One closed solid of a spacecraft.

    Attributes:
        kind: what the part is (``"bus_box"``, ``"solar_panel"``, ``"dish"``...).
        material: one of :data:`sq_mitsuba.render.materials.MATERIALS`.
        solid: the closed solid.
    """

    kind: str
    material: str
    solid: Solid

    def __post_init__(self) -> None:
        material_index(self.material)  # fail early on a typo in a material tag


# --------------------------------------------------------------------------- geometry helpers

def rotation_about(axis: Sequence[float], degrees: float) -> np.ndarray:
    """3x3 rotation by ``degrees`` about ``axis`` (right-handed, Rodrigues)."""
    k = np.asarray(axis, dtype=float)
    k = k / np.linalg.norm(k)
    a = np.radians(degrees)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(a) * kx + (1 - np.cos(a)) * (kx @ kx)


def frame_z_to(direction: Sequence[float]) -> np.ndarray:
    """A rotation taking +z to ``direction`` (the shortest one; x and y follow)."""
    d = np.asarray(direction, dtype=float)
    d = d / np.linalg.norm(d)
    z = np.array([0.0, 0.0, 1.0])
    c = float(z @ d)
    if c > 1 - 1e-12:
        return np.eye(3)
    if c < -1 + 1e-12:
        return np.diag([1.0, -1.0, -1.0])
    axis = np.cross(z, d)
    return rotation_about(axis, np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def transform_solid(solid: Solid, rotation: np.ndarray | None = None,
                    translation: Sequence[float] = (0.0, 0.0, 0.0)) -> Solid:
    """``solid`` rotated by ``rotation`` (3x3) about the origin, then translated."""
    matrix = np.zeros((3, 4))
    matrix[:, :3] = np.eye(3) if rotation is None else rotation
    matrix[:, 3] = translation
    return solid.transform(matrix)


def place(parts: Sequence[Part], rotation: np.ndarray | None = None,
          translation: Sequence[float] = (0.0, 0.0, 0.0)) -> list[Part]:
    """Parts moved rigidly: rotated about the origin, then translated."""
    return [Part(p.kind, p.material, transform_solid(p.solid, rotation, translation))
            for p in parts]


def box(size: Sequence[float], center: Sequence[float] = (0.0, 0.0, 0.0)) -> Solid:
    """Axis-aligned box of ``size`` centred at ``center``."""
    return Solid.cube(tuple(float(s) for s in size), True).translate(tuple(center))


def prism(sides: int, radius: float, height: float, radius_top: float | None = None) -> Solid:
    """Regular ``sides``-gon prism (or frustum) along z, centred at the origin.

    ``radius`` is the circumradius; a flat side faces +x for even ``sides``.
    """
    top = radius if radius_top is None else radius_top
    solid = Solid.cylinder(float(height), float(radius), float(top), int(sides), True)
    return solid.rotate((0.0, 0.0, 180.0 / sides)) if sides % 2 == 0 else solid


def rod(start: Sequence[float], end: Sequence[float], radius: float, sides: int = 8) -> Solid:
    """A cylinder of ``radius`` from ``start`` to ``end``."""
    p0, p1 = np.asarray(start, float), np.asarray(end, float)
    length = float(np.linalg.norm(p1 - p0))
    solid = Solid.cylinder(length, float(radius), float(radius), sides, True)
    return transform_solid(solid, frame_z_to(p1 - p0), (p0 + p1) / 2)


# ----------------------------------------------------------------------------------- buses

def box_bus(size: Sequence[float], material: str = "gold_mli") -> list[Part]:
    """A box bus centred at the origin."""
    return [Part("bus_box", material, box(size))]


def prism_bus(sides: int, radius: float, height: float, material: str = "gold_mli") -> list[Part]:
    """A prism bus along z: 6 = hexagonal, 8 = octagonal, >= 16 = cylindrical."""
    kind = {6: "bus_hexagonal", 8: "bus_octagonal"}.get(sides, "bus_cylinder")
    return [Part(kind, material, prism(sides, radius, height))]


CUBESAT_UNITS: dict[int, tuple[int, int, int]] = {
    1: (1, 1, 1), 2: (1, 1, 2), 3: (1, 1, 3), 6: (2, 1, 3), 12: (2, 2, 3),
}
CUBESAT_UNIT_M = 0.1


CUBESAT_RAIL_M = 0.0085  # side of the four corner rails of the CubeSat standard


def cubesat_body_size(units: int) -> np.ndarray:
    """Side lengths (3,) of a CubeSat's body between its rails (rails reach ``size / 2``)."""
    if units not in CUBESAT_UNITS:
        raise ValueError(f"units: expected one of {sorted(CUBESAT_UNITS)}, got {units}")
    size = np.array(CUBESAT_UNITS[units], float) * CUBESAT_UNIT_M
    return size - 1.6 * CUBESAT_RAIL_M * np.array([1.0, 1.0, 0.0])


def cubesat_bus(units: int, thin: float, cells_on: Sequence[str] = ("+x", "-x", "+y", "-y"),
                ) -> list[Part]:
    """A CubeSat of ``units`` U (1, 2, 3, 6, 12) along z, with body-mounted cells and rails.

    The rails stand 0.2 of their width into the body, so body and rails are one piece.
    """
    body = cubesat_body_size(units)
    size = np.array(CUBESAT_UNITS[units], float) * CUBESAT_UNIT_M
    rail = CUBESAT_RAIL_M
    parts = [Part("cubesat_body", "aluminium", box(body))]
    for sx in (-1, 1):  # the four corner rails of the CubeSat standard
        for sy in (-1, 1):
            center = (sx * (size[0] / 2 - rail / 2), sy * (size[1] / 2 - rail / 2), 0.0)
            parts.append(Part("cubesat_rail", "aluminium",
                              box((rail, rail, size[2] + 0.014), center)))
    parts += body_cells(body, thin, cells_on, margin=0.005)
    return parts


def body_cells(bus_size: Sequence[float], thin: float, faces: Sequence[str],
               margin: float = 0.02) -> list[Part]:
    """Body-mounted solar cells: thin plates on the named faces (``"+x"``...) of a box."""
    size = np.asarray(bus_size, float)
    parts = []
    for face in faces:
        axis = "xyz".index(face[1])
        sign = 1.0 if face[0] == "+" else -1.0
        plate = size.copy() - 2 * margin
        plate[axis] = thin
        center = np.zeros(3)
        center[axis] = sign * (size[axis] / 2 + thin / 2 - thin * 0.25)  # overlaps the bus
        parts.append(Part("body_cells", "solar_cell", box(plate, center)))
    return parts


# ------------------------------------------------------------------------------ solar arrays

def solar_wing(span: float, chord: float, panels: int, thin: float, yoke: float = 0.3,
               gap: float = 0.02, cant_deg: float = 0.0, yoke_radius: float = 0.03,
               embed: float | None = None) -> list[Part]:
    """One deployed wing along +x from the origin: a yoke, then ``panels`` segments.

    ``span`` is the length of the cells, ``chord`` their width (along y); ``cant_deg`` turns
    the panels about the wing axis (x). Consecutive panels are joined by short hinges so
    the wing is one connected solid. The yoke starts ``embed`` (default 3 yoke radii) behind
    the origin, inside the surface the wing is mounted on.
    """
    embed = 3 * yoke_radius if embed is None else embed
    parts = [Part("yoke", "aluminium", rod((-embed, 0, 0), (yoke + 0.01, 0, 0), yoke_radius)),
             Part("yoke", "aluminium",
                  box((2 * yoke_radius, chord * 0.6, 2 * yoke_radius), (yoke, 0, 0)))]
    length = (span - gap * (panels - 1)) / panels
    cant = rotation_about((1, 0, 0), cant_deg)
    for i in range(panels):
        x0 = yoke + i * (length + gap)
        panel = box((length, chord, thin), (x0 + length / 2, 0, 0))
        parts.append(Part("solar_panel", "solar_cell", transform_solid(panel, cant)))
        if i:
            for y in (-chord / 3, chord / 3):  # hinges bridging the gap between panels
                hinge = box((gap + 0.02, 0.04, thin), (x0 - gap / 2, y, 0))
                parts.append(Part("panel_hinge", "aluminium", transform_solid(hinge, cant)))
    return parts


def wing_pair(span: float, chord: float, panels: int, thin: float, offset: float,
              yoke: float = 0.3, cant_deg: float = 0.0, yoke_radius: float = 0.03,
              ) -> list[Part]:
    """Two symmetric wings along +x and -x, their roots at x = +-``offset``."""
    wing = solar_wing(span, chord, panels, thin, yoke=yoke, cant_deg=cant_deg,
                      yoke_radius=yoke_radius)
    return (place(wing, None, (offset, 0, 0))
            + place(wing, rotation_about((0, 0, 1), 180), (-offset, 0, 0)))


# ---------------------------------------------------------------------------------- antennas

def parabolic_dish(diameter: float, depth: float, thin: float, feed: bool = True,
                   material: str = "antenna_white", steps: int = 10) -> list[Part]:
    """A paraboloid shell of ``diameter`` and ``depth`` opening towards +z, vertex at origin.

    The shell is ``thin`` thick; with ``feed`` a strut carries a feed horn at the focus.
    """
    radius = diameter / 2
    r = np.linspace(0.0, radius, steps + 1)
    z = depth * (r / radius) ** 2
    outline = [(float(a), float(b)) for a, b in zip(r, z, strict=True)]
    outline += [(float(a), float(b) + thin) for a, b in zip(r[::-1], z[::-1], strict=True)]
    shell = Solid.revolve(manifold3d.CrossSection([outline]), CIRCLE_SEGMENTS)
    parts = [Part("dish", material, shell)]
    if feed:
        focal = radius**2 / (4 * depth)
        strut_r = max(thin * 0.8, diameter * 0.008)
        parts.append(Part("dish_feed_strut", "aluminium", rod((0, 0, 0), (0, 0, focal), strut_r)))
        feed_r = diameter * 0.06
        parts.append(Part("dish_feed", "antenna_white",
                          transform_solid(prism(12, feed_r * 0.6, feed_r * 1.5, feed_r),
                                          None, (0, 0, focal))))
    return parts


def horn_antenna(length: float, aperture: float, pyramidal: bool = True) -> list[Part]:
    """A horn antenna along +z from the origin (throat) to its aperture.

    A waveguide stub of a fifth of the length reaches behind the origin (the mounting).
    """
    throat = aperture * 0.25
    stub = 0.2 * length
    if pyramidal:
        solid = Solid.batch_hull([box((throat, throat, 1e-3), (0, 0, 0)),
                                  box((aperture, aperture * 0.75, 1e-3), (0, 0, length))])
        waveguide = box((throat, throat, stub + 0.01 * length), (0, 0, -stub / 2))
    else:
        solid = transform_solid(prism(16, throat / 2, length, aperture / 2), None,
                                (0, 0, length / 2))
        waveguide = transform_solid(prism(16, throat / 2, stub + 0.01 * length), None,
                                    (0, 0, -stub / 2))
    return [Part("horn_antenna", "aluminium", solid + waveguide)]


# ------------------------------------------------------------------------- booms and masts

def boom(length: float, radius: float, material: str = "aluminium", embed: float = 0.1,
         ) -> list[Part]:
    """A boom along +x from the origin, its root ``embed`` behind the origin."""
    return [Part("boom", material, rod((-embed, 0, 0), (length, 0, 0), radius))]


def magnetometer_mast(length: float, radius: float, embed: float = 0.1) -> list[Part]:
    """A mast along +x with a sensor at the tip and one half way; root ``embed`` behind."""
    s = radius * 4
    return [Part("magnetometer_mast", "dark_composite",
                 rod((-embed, 0, 0), (length, 0, 0), radius)),
            Part("magnetometer", "white_paint", box((s * 1.5, s, s), (length, 0, 0))),
            Part("magnetometer", "white_paint", box((s, s, s), (length * 0.55, 0, 0)))]


def truss(length: float, width: float, rod_radius: float, bays: int) -> list[Part]:
    """A square lattice truss along +x: four longerons, frames and diagonals per bay."""
    h = width / 2
    corners = [(-h, -h), (h, -h), (h, h), (-h, h)]
    solids = [rod((0, y, z), (length, y, z), rod_radius, 6) for y, z in corners]
    for i in range(bays + 1):
        x = length * i / bays
        for a, b in zip(corners, corners[1:] + corners[:1], strict=True):
            solids.append(rod((x, *a), (x, *b), rod_radius * 0.8, 6))
        if i < bays:
            x1 = length * (i + 1) / bays
            a, b = corners[i % 2], corners[(i % 2) + 2]
            solids.append(rod((x, *a), (x1, *b), rod_radius * 0.7, 6))
    return [Part("truss", "dark_composite", s) for s in solids]


# ---------------------------------------------------------------------------- instruments

def instrument_box(size: Sequence[float], material: str = "white_paint",
                   aperture: bool = True) -> list[Part]:
    """A box instrument centred at the origin, with a round aperture on +z."""
    parts = [Part("instrument", material, box(size))]
    if aperture:
        r = 0.3 * min(size[0], size[1])
        parts.append(Part("instrument_aperture", "dark_composite",
                          transform_solid(prism(16, r, size[2] * 0.3), None,
                                          (0, 0, size[2] / 2 + size[2] * 0.1))))
    return parts


def telescope_tube(radius: float, length: float, thin: float, door: bool = True,
                   material: str = "silver_mli") -> list[Part]:
    """A telescope tube along +z from the origin, with an aperture ring and an open door."""
    parts = [Part("telescope_tube", material,
                  transform_solid(prism(CIRCLE_SEGMENTS, radius, length), None,
                                  (0, 0, length / 2))),
             Part("aperture_ring", "aluminium",
                  transform_solid(prism(CIRCLE_SEGMENTS, radius * 1.06, length * 0.04), None,
                                  (0, 0, length * 0.98)))]
    if door:  # hinged at the rim, opened 100 degrees
        plate = transform_solid(prism(CIRCLE_SEGMENTS, radius * 1.02, thin), None,
                                (radius * 1.02, 0, 0))
        opened = transform_solid(plate, rotation_about((0, 1, 0), -100),
                                 (radius * 1.0, 0, length * 0.99))  # hinge inside the ring
        parts.append(Part("aperture_door", "silver_mli", opened))
    return parts


def star_tracker(size: float) -> list[Part]:
    """A star tracker mounted at the origin, looking along +z: an electronics box (its base
    a fifth of ``size`` behind the origin, in the mounting surface) and a conical baffle."""
    return [Part("star_tracker", "aluminium", box((size, size, size * 0.7), (0, 0, size * 0.15))),
            Part("star_tracker_baffle", "dark_composite",
                 transform_solid(prism(16, size * 0.3, size * 1.2, size * 0.45), None,
                                 (0, 0, size * 1.0)))]


def thruster_nozzle(length: float, exit_radius: float) -> list[Part]:
    """A thruster nozzle: throat at the origin, bell opening towards -z, and a combustion
    chamber reaching ``0.4 * length`` behind the origin (into the mounting surface)."""
    throat = exit_radius * 0.35
    bell = transform_solid(prism(16, exit_radius, length, throat), None, (0, 0, -length / 2))
    chamber = transform_solid(prism(16, throat * 1.3, 0.45 * length), None,
                              (0, 0, 0.175 * length))
    return [Part("thruster_nozzle", "aluminium", bell + chamber)]


# ------------------------------------------------------------------------------- shielding

def sunshield(width: float, height: float, thin: float, material: str = "silver_mli"
              ) -> list[Part]:
    """A flat sunshield plate in the x-y plane, centred at the origin."""
    return [Part("sunshield", material, box((width, height, thin)))]


def heat_shield(radius: float, thickness: float) -> list[Part]:
    """A round heat shield in the x-y plane: carbon foam with a white sun-facing coat on +z."""
    core = prism(CIRCLE_SEGMENTS, radius, thickness)
    coat = transform_solid(prism(CIRCLE_SEGMENTS, radius * 0.985, thickness * 0.2), None,
                           (0, 0, thickness * 0.55))
    return [Part("heat_shield", "dark_composite", core),
            Part("heat_shield_coat", "white_paint", coat)]


def lander_leg(height: float, splay: float, radius: float) -> list[Part]:
    """A landing leg from the origin down to a footpad ``height`` below, ``splay`` out in +x."""
    foot = (splay, 0.0, -height)
    return [Part("landing_leg", "aluminium", rod((0, 0, 0), foot, radius)),
            Part("footpad", "aluminium",
                 transform_solid(prism(16, radius * 3.5, radius * 1.2), None, foot))]


# ------------------------------------------------------ parts of the compositional generator

def circular_wing(radius: float, thin: float, yoke: float = 0.3, sides: int = 14,
                  yoke_radius: float = 0.03, embed: float | None = None) -> list[Part]:
    """A round (UltraFlex-like) array along +x: a yoke, then a disc of cells facing +z.

    The disc (``sides``-gon of circumradius ``radius``) is centred at ``yoke + radius``; the
    yoke runs from ``embed`` behind the origin a fifth of the radius into the disc, and a hub
    at the disc's centre carries the gores' ribs (one rib along the yoke's line).
    """
    embed = 3 * yoke_radius if embed is None else embed
    centre = yoke + radius
    disc = transform_solid(prism(sides, radius, thin), None, (centre, 0, 0))
    hub = transform_solid(prism(12, radius * 0.08, thin * 3), None, (centre, 0, 0))
    return [Part("yoke", "aluminium", rod((-embed, 0, 0), (yoke + 0.2 * radius, 0, 0),
                                          yoke_radius)),
            Part("solar_panel", "solar_cell", disc),
            Part("array_hub", "aluminium", hub),
            Part("panel_hinge", "aluminium",
                 rod((yoke + 0.1 * radius, 0, 0), (centre, 0, 0), yoke_radius * 0.8, 6))]


def rtg(length: float, radius: float, fins: int = 6) -> list[Part]:
    """A radioisotope generator along z, centred at the origin: a finned dark cylinder."""
    core = prism(12, radius, length)
    parts = [Part("rtg", "dark_composite", core)]
    fin = box((radius * 0.9, radius * 0.14, length * 0.9), (radius * 1.3, 0, 0))
    for k in range(fins):
        parts.append(Part("rtg_fin", "dark_composite",
                          transform_solid(fin, rotation_about((0, 0, 1), 360 * k / fins))))
    return parts


def flat_panel(kind: str, material: str, width: float, height: float, thickness: float,
               ) -> list[Part]:
    """A flat plate (radiator, phased array, sunshade) in the x-y plane, centred at origin."""
    return [Part(kind, material, box((width, height, thickness)))]


def pressurised_module(radius: float, length: float, material: str = "white_paint",
                       cone: float = 0.25) -> list[Part]:
    """A pressurised module along z, centred at the origin: a cylinder with tapered end cones
    (``cone`` of the length each) and a docking ring at each end."""
    body_len = length * (1 - 2 * cone)
    parts = [Part("module", material, prism(CIRCLE_SEGMENTS, radius, body_len))]
    for sign in (1, -1):
        frustum = prism(CIRCLE_SEGMENTS, radius, length * cone * 1.02, radius * 0.55)
        if sign < 0:
            frustum = transform_solid(frustum, rotation_about((1, 0, 0), 180))
        parts.append(Part("module_cone", material, transform_solid(
            frustum, None, (0, 0, sign * (body_len / 2 + length * cone / 2 - 0.01 * length)))))
        parts.append(Part("docking_ring", "aluminium", transform_solid(
            prism(16, radius * 0.45, length * 0.06), None,
            (0, 0, sign * (length / 2 + 0.01 * length)))))
    return parts


def capsule(radius: float, height: float, thin: float) -> list[Part]:
    """A crew or cargo capsule: a cone frustum from its heat shield at the origin up along
    +z, the heat shield a flat disc centred on the origin, a tenth of the height thick (at
    least ``thin``): it reaches half that behind the origin."""
    cone = transform_solid(prism(CIRCLE_SEGMENTS, radius, height, radius * 0.4), None,
                           (0, 0, height / 2))
    shield = transform_solid(prism(CIRCLE_SEGMENTS, radius * 1.02, max(thin, 0.1 * height)),
                             None, (0, 0, 0))
    hatch = transform_solid(prism(16, radius * 0.25, height * 0.12), None, (0, 0, height))
    return [Part("capsule", "white_paint", cone), Part("heat_shield", "dark_composite", shield),
            Part("docking_port", "aluminium", hatch)]


def segmented_mirror(segment: float, rings: int, focal: float, thin: float) -> list[Part]:
    """A segmented primary mirror opening towards +z, vertex at the origin: hexagonal
    segments (circumradius ``segment``) on ``rings`` rings of a hexagonal grid around an
    empty centre, each sunk to the paraboloid of ``focal`` length, on a backplane."""
    pitch = segment * np.sqrt(3)  # centre-to-centre distance of touching flat-topped hexes
    cells = []
    for q in range(-rings, rings + 1):
        for r in range(-rings, rings + 1):
            s = -q - r
            if max(abs(q), abs(r), abs(s)) == 0 or max(abs(q), abs(r), abs(s)) > rings:
                continue
            x = pitch * (q + r / 2)
            y = pitch * r * np.sqrt(3) / 2
            cells.append((x, y))
    parts = []
    thick = max(2 * thin, segment * 0.12)
    for x, y in cells:  # columns from the backplane up to the paraboloid, 4 % wider than
        z = (x * x + y * y) / (4 * focal)  # the pitch, so neighbours overlap
        hexagon = transform_solid(prism(6, segment * 1.04, z + thick), None, (x, y, z / 2))
        parts.append(Part("mirror_segment", "gold_mli", hexagon))
    reach = pitch * rings
    parts.append(Part("mirror_backplane", "dark_composite",
                      box((reach * 1.2, reach * 0.9, thick * 2), (0, 0, -thick))))
    return parts


def layered_shield(length: float, width: float, layers: int, gap: float, thin: float,
                   ) -> list[Part]:
    """A layered sunshield of ``layers`` hexagonal (kite-like) membranes in x-y planes,
    stacked from the origin towards -z ``gap`` apart, joined by posts through all layers."""
    h, w = length / 2, width / 2
    outline = [(h, 0.0), (h * 0.35, w), (-h * 0.35, w), (-h, 0.0), (-h * 0.35, -w),
               (h * 0.35, -w)]
    membrane = Solid.extrude(manifold3d.CrossSection([outline]), float(thin))
    parts = []
    for k in range(layers):
        scale = 1.0 - 0.04 * k
        layer = membrane.scale((scale, scale, 1.0)).translate((0.0, 0.0, -k * gap - thin / 2))
        parts.append(Part("sunshield", "silver_mli", layer))
    depth = (layers - 1) * gap + 2 * thin
    for x, y in ((0.0, 0.0), (h * 0.6, 0.0), (-h * 0.6, 0.0), (0.0, w * 0.6), (0.0, -w * 0.6)):
        parts.append(Part("sunshield_post", "aluminium",
                          rod((x, y, thin), (x, y, -depth), max(thin, 0.02 * width), 6)))
    return parts


def ion_thruster(radius: float, length: float) -> list[Part]:
    """A gridded ion thruster: its exit plane ``length`` below the origin (exhaust towards -z),
    its body reaching 0.4 of the length behind the origin into the mounting."""
    body = transform_solid(prism(CIRCLE_SEGMENTS, radius, 1.4 * length, radius * 0.8), None,
                           (0, 0, -0.3 * length))
    grid = transform_solid(prism(CIRCLE_SEGMENTS, radius * 0.92, length * 0.1), None,
                           (0, 0, -length))
    return [Part("ion_thruster", "aluminium", body), Part("ion_grid", "dark_composite", grid)]
