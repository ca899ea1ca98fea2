"""Archetype families: seeded recipes that assemble parts into spacecraft of a real class.

Each recipe takes a ``numpy.random.Generator`` and the thickness ``thin`` of thin parts
(panels, sunshields, dish shells) and returns the parts in the spacecraft's body frame.
Recipes draw all their random numbers from the generator in a fixed order, so the same
generator state gives the same spacecraft.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from sq_mitsuba.spacecraft import parts as P
from sq_mitsuba.spacecraft.parts import Part, place, rotation_about

Recipe = Callable[[np.random.Generator, float], list[Part]]

_X, _Y, _Z = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)
MLI = ("gold_mli", "silver_mli")


def _pick(rng: np.random.Generator, options: tuple) -> object:
    return options[int(rng.integers(len(options)))]


def _dish_on(rng: np.random.Generator, thin: float, diameter: float, at: tuple,
             facing: tuple, mast: float = 0.0) -> list[Part]:
    """A dish on an optional short mast at ``at``, opening towards ``facing``."""
    depth = diameter * rng.uniform(0.12, 0.25)
    dish = P.parabolic_dish(diameter, depth, thin, feed=bool(rng.random() < 0.8))
    parts = place(dish, None, (0, 0, mast))
    if mast > 0:
        parts += [Part("antenna_mast", "aluminium", P.rod((0, 0, 0), (0, 0, mast + thin), 0.04))]
    return place(parts, P.frame_z_to(facing), at)


def twin_wing(rng: np.random.Generator, thin: float) -> list[Part]:
    """Box bus with two symmetric multi-panel wings (communications / Earth observation)."""
    bx, by, bz = rng.uniform(1.2, 2.2), rng.uniform(1.2, 2.2), rng.uniform(1.5, 3.0)
    parts = P.box_bus((bx, by, bz), _pick(rng, MLI))
    span, chord = rng.uniform(3.0, 7.0), rng.uniform(1.2, 2.2)
    panels = int(rng.integers(2, 6))
    parts += P.wing_pair(span, chord, panels, thin, bx / 2, yoke=rng.uniform(0.3, 1.0),
                         cant_deg=rng.uniform(-30, 30) if rng.random() < 0.4 else 0.0)
    parts += _dish_on(rng, thin, rng.uniform(0.8, 2.0), (0, 0, bz / 2), _Z,
                      mast=rng.uniform(0.0, 0.6))
    if rng.random() < 0.7:
        parts += place(P.parabolic_dish(rng.uniform(0.6, 1.4), 0.2, thin),
                       P.frame_z_to((0, 1, 0.3)), (0, by / 2, bz * 0.3))
    parts += place(P.thruster_nozzle(0.3, 0.15), None, (0, 0, -bz / 2))
    return parts


def single_wing(rng: np.random.Generator, thin: float) -> list[Part]:
    """Box bus with one long wing on one side and nadir instruments (EO-1, Aqua, Aura)."""
    bx, by, bz = rng.uniform(1.5, 3.0), rng.uniform(1.5, 2.5), rng.uniform(2.0, 5.0)
    parts = P.box_bus((bx, by, bz), _pick(rng, MLI))
    wing = P.solar_wing(rng.uniform(4.0, 12.0), rng.uniform(1.5, 3.0), int(rng.integers(3, 8)),
                        thin, yoke=rng.uniform(0.5, 2.0), cant_deg=rng.uniform(-20, 20))
    tilt = rotation_about(_X, rng.uniform(0, 60))
    parts += place(place(wing, tilt), None, (bx / 2, 0, bz * rng.uniform(-0.3, 0.3)))
    for _ in range(int(rng.integers(2, 5))):
        s = rng.uniform(0.4, 1.0, size=3)
        at = (rng.uniform(-bx / 3, bx / 3), rng.uniform(-by / 3, by / 3), -bz / 2 - s[2] / 2)
        parts += place(P.instrument_box(s, _pick(rng, ("white_paint", "silver_mli"))),
                       P.frame_z_to((0, 0, -1)), at)
    parts += place(P.star_tracker(0.25), None, (-bx / 4, by / 4, bz / 2 + 0.15))
    if rng.random() < 0.6:
        parts += _dish_on(rng, thin, rng.uniform(0.6, 1.2), (-bx / 2, 0, 0), (-1, 0, 0.2), 0.5)
    return parts


def tri_wing(rng: np.random.Generator, thin: float) -> list[Part]:
    """Hexagonal bus, three long wings at 120 degrees, top high-gain dish (Juno)."""
    radius, height = rng.uniform(1.5, 2.2), rng.uniform(1.5, 3.0)
    parts = P.prism_bus(6, radius, height, _pick(rng, MLI))
    span, chord = rng.uniform(6.0, 9.0), rng.uniform(2.0, 2.8)
    panels = int(rng.integers(3, 6))
    phase = rng.uniform(0, 60)
    for k in range(3):
        wing = P.solar_wing(span, chord, panels, thin, yoke=0.4)
        parts += place(wing, rotation_about(_Z, phase + 120 * k),
                       rotation_about(_Z, phase + 120 * k) @ np.array([radius * 0.85, 0, 0]))
    parts += _dish_on(rng, thin, radius * rng.uniform(1.2, 1.7), (0, 0, height / 2), _Z, 0.1)
    parts += place(P.magnetometer_mast(rng.uniform(1.0, 2.0), 0.05),
                   rotation_about(_Z, phase + 60), (0, 0, height / 4))
    parts += place(P.thruster_nozzle(0.5, 0.25), None, (0, 0, -height / 2))
    return parts


def dish_probe(rng: np.random.Generator, thin: float) -> list[Part]:
    """Decagonal bus under a large high-gain dish, RTG booms and a long magnetometer boom
    (Voyager, Galileo, Cassini)."""
    bus_r, bus_h = rng.uniform(0.8, 1.4), rng.uniform(0.5, 1.2)
    parts = P.prism_bus(10, bus_r, bus_h, _pick(rng, ("aluminium", "gold_mli")))
    dish_d = rng.uniform(3.0, 4.5)
    parts += _dish_on(rng, thin, dish_d, (0, 0, bus_h / 2), _Z, mast=rng.uniform(0.1, 0.6))
    if rng.random() < 0.5:  # Cassini-like tall stack below the bus
        tank_h = rng.uniform(2.0, 4.0)
        parts += place(P.prism_bus(P.CIRCLE_SEGMENTS, bus_r * 0.8, tank_h, "gold_mli"), None,
                       (0, 0, -bus_h / 2 - tank_h / 2))
        parts += place(P.thruster_nozzle(0.8, 0.4), None, (0, 0, -bus_h / 2 - tank_h))
    rtg_angle = rng.uniform(0, 360)
    for sign in (1, -1) if rng.random() < 0.5 else (1,):
        direction = rotation_about(_Z, rtg_angle + (0 if sign > 0 else 180))
        length = rng.uniform(1.5, 3.0)
        arm = P.boom(length, 0.05) + place(
            [Part("rtg", "dark_composite", P.prism(8, 0.22, 1.1))],
            P.frame_z_to(_X), (length, 0, 0))
        parts += place(arm, direction, direction @ np.array([bus_r * 0.9, 0, 0]))
    parts += place(P.magnetometer_mast(rng.uniform(5.0, 11.0), 0.06),
                   rotation_about(_Z, rtg_angle + 90), (0, 0, 0))
    return parts


def telescope(rng: np.random.Generator, thin: float) -> list[Part]:
    """Long telescope tube with an aft equipment section and two wings (HST, Chandra, XMM)."""
    radius, length = rng.uniform(1.0, 2.2), rng.uniform(8.0, 13.0)
    parts = P.telescope_tube(radius, length, thin, door=bool(rng.random() < 0.7))
    aft_len = length * rng.uniform(0.15, 0.3)
    parts += place(P.prism_bus(int(_pick(rng, (8, 32))), radius * 1.1, aft_len,
                               _pick(rng, MLI)), None, (0, 0, -aft_len / 2))
    span, chord = rng.uniform(4.0, 9.0), rng.uniform(1.8, 3.0)
    wing = P.solar_wing(span, chord, int(rng.integers(1, 4)), thin, yoke=0.4,
                        cant_deg=90.0 * (rng.random() < 0.5))
    z_wing = length * rng.uniform(0.15, 0.45)
    parts += place(place(wing, P.frame_z_to(_Z)), None, (radius * 0.95, 0, z_wing))
    parts += place(wing, rotation_about(_Z, 180), (-radius * 0.95, 0, z_wing))
    for sign in (1, -1):
        parts += place(P.parabolic_dish(0.9, 0.15, thin),
                       P.frame_z_to((0, sign, 0)),
                       (0, sign * (radius + 1.0), length * 0.3))
        parts += [Part("antenna_mast", "aluminium",
                       P.rod((0, 0, length * 0.3), (0, sign * (radius + 1.0), length * 0.3),
                             0.05))]
    parts += place(P.star_tracker(0.4), None, (radius * 0.6, radius * 0.5, -aft_len - 0.1))
    return parts


def cubesat(rng: np.random.Generator, thin: float) -> list[Part]:
    """A 1U-12U CubeSat with body cells and optional deployable panels and whip antennas."""
    units = int(_pick(rng, (1, 2, 3, 3, 6, 6, 12)))
    size = np.array(P.CUBESAT_UNITS[units], float) * P.CUBESAT_UNIT_M
    parts = P.cubesat_bus(units, thin)
    style = int(rng.integers(3))
    if style > 0:  # deployed panels hinged at the top (+z) edge of the +-x and +-y faces
        faces = (0, 1, 2, 3) if style == 2 else (0, 2)
        for k in faces:
            angle = 90 * k
            half = size[0] / 2 if k % 2 == 0 else size[1] / 2
            width = size[1] if k % 2 == 0 else size[0]
            n = int(rng.integers(1, 4))
            wing = P.solar_wing(size[2] * n, width * 0.95, n, thin, yoke=0.02, gap=0.005,
                                yoke_radius=0.006)
            tilt = rotation_about(_Y, -rng.uniform(0, 60))
            parts += place(place(wing, tilt), rotation_about(_Z, angle),
                           rotation_about(_Z, angle) @ np.array([half, 0, size[2] / 2]))
    for k in range(int(rng.integers(0, 5))):  # tape-measure whip antennas
        direction = rotation_about(_Z, 90 * k + 45) @ np.array([1.0, 0, 0])
        root = np.array([0, 0, -size[2] / 2]) + direction * min(size[:2]) * 0.3
        parts.append(Part("whip_antenna", "aluminium",
                          P.rod(root, root + direction * rng.uniform(0.15, 0.5), 0.003, 6)))
    if units >= 6 and rng.random() < 0.5:
        parts += place(P.parabolic_dish(size[0] * 0.9, size[0] * 0.15, thin), None,
                       (0, 0, size[2] / 2 + 0.02))
    return parts


def solar_probe(rng: np.random.Generator, thin: float) -> list[Part]:
    """Octagonal bus behind a large heat shield on a truss, small canted wings (Parker)."""
    bus_r, bus_h = rng.uniform(0.7, 1.1), rng.uniform(0.8, 1.4)
    parts = P.prism_bus(8, bus_r, bus_h, _pick(rng, ("aluminium", "silver_mli")))
    gap = rng.uniform(0.6, 1.2)
    shield_r = bus_r * rng.uniform(1.6, 2.2)
    parts += place(P.heat_shield(shield_r, rng.uniform(0.08, 0.15)), None,
                   (0, 0, bus_h / 2 + gap))
    for k in range(6):  # struts from the bus top to the shield
        a = rotation_about(_Z, 60 * k)
        p0 = a @ np.array([bus_r * 0.6, 0, bus_h / 2 - 0.01])
        p1 = a @ np.array([bus_r * 0.9, 0, bus_h / 2 + gap])
        parts.append(Part("truss", "dark_composite", P.rod(p0, p1, 0.03, 6)))
    span, chord = rng.uniform(1.0, 1.8), rng.uniform(0.6, 0.9)
    cant = rng.uniform(20, 70)
    for sign in (1, -1):
        wing = P.solar_wing(span, chord, 1, thin, yoke=0.3, cant_deg=sign * cant)
        wing = place(wing, rotation_about(_Y, -rng.uniform(10, 40)))
        parts += place(wing, rotation_about(_Z, 0 if sign > 0 else 180),
                       (sign * bus_r * 0.9, 0, -bus_h / 4))
    parts += place(P.parabolic_dish(rng.uniform(0.5, 0.8), 0.1, thin),
                   P.frame_z_to((0, -1, -0.5)), (0, -bus_r * 0.9, -bus_h / 2))
    parts += place(P.magnetometer_mast(rng.uniform(2.0, 3.5), 0.03),
                   P.frame_z_to((0, 0, -1)) @ P.frame_z_to(_X), (0, 0, -bus_h / 2))
    return parts


def lander(rng: np.random.Generator, thin: float) -> list[Part]:
    """Hexagonal or octagonal deck on three or four legs, round-ish wings, descent engines
    (Phoenix, InSight, Surveyor)."""
    sides = int(_pick(rng, (6, 8)))
    deck_r, deck_h = rng.uniform(0.6, 1.3), rng.uniform(0.3, 0.8)
    parts = P.prism_bus(sides, deck_r, deck_h, _pick(rng, ("white_paint", "gold_mli")))
    legs = int(_pick(rng, (3, 4)))
    leg_h = rng.uniform(0.6, 1.0)
    for k in range(legs):
        a = rotation_about(_Z, 360 * k / legs + 30)
        parts += place(P.lander_leg(leg_h, rng.uniform(0.3, 0.6), 0.04), a,
                       a @ np.array([deck_r * 0.8, 0, -deck_h / 2 + 0.05]))
    # decagonal "round" wings, like Phoenix's and InSight's
    wing_r = rng.uniform(0.6, 1.5)
    wing_sides = int(_pick(rng, (4, 10)))  # square (Surveyor-like) or round (Phoenix-like)
    for sign in (1, -1):
        disc = Part("solar_panel", "solar_cell", P.prism(wing_sides, wing_r, thin))
        parts += [Part(disc.kind, disc.material,
                       P.transform_solid(disc.solid, None,
                                         (sign * (deck_r + wing_r * 0.95), 0, deck_h / 2)))]
        parts.append(Part("yoke", "aluminium",
                          P.box((0.4, 0.1, 0.06), (sign * (deck_r + 0.1), 0, deck_h / 2))))
    for k in range(int(rng.integers(3, 6))):
        a = rotation_about(_Z, 360 * k / 5 + 10)
        parts += place(P.thruster_nozzle(0.2, 0.08), None,
                       a @ np.array([deck_r * 0.4, 0, -deck_h / 2]))
    parts += place(P.instrument_box((0.25, 0.25, 0.25), "white_paint"), None,
                   (0, deck_r * 0.3, deck_h / 2 + 0.12))
    arm = P.rod((0, 0, 0), (rng.uniform(1.0, 1.6), 0, rng.uniform(0.2, 0.6)), 0.03)
    parts.append(Part("robotic_arm", "aluminium",
                      P.transform_solid(arm, rotation_about(_Z, 90), (0, 0, deck_h / 2))))
    if rng.random() < 0.7:  # camera mast
        parts += [Part("camera_mast", "aluminium",
                       P.rod((0, -deck_r * 0.5, deck_h / 2), (0, -deck_r * 0.5, 1.4), 0.03))]
        parts += [Part("camera", "white_paint", P.box((0.2, 0.15, 0.15),
                                                      (0, -deck_r * 0.5, 1.45)))]
    return parts


def sunshade_observatory(rng: np.random.Generator, thin: float) -> list[Part]:
    """Cylindrical service module, a telescope, and a large sunshield with cells
    (Herschel, Planck, Gaia)."""
    bus_r, bus_h = rng.uniform(1.3, 2.0), rng.uniform(1.2, 2.0)
    parts = P.prism_bus(int(_pick(rng, (8, 32))), bus_r, bus_h, _pick(rng, MLI))
    tele_r = bus_r * rng.uniform(0.5, 0.9)
    tele_h = rng.uniform(2.0, 4.0)
    parts += place(P.telescope_tube(tele_r, tele_h, thin, door=False), None, (0, 0, bus_h / 2))
    if rng.random() < 0.5:  # Herschel: tall flat sunshade on one side
        shade_w, shade_h = bus_r * 2.2, bus_h + tele_h
        shade = P.sunshield(shade_w, shade_h, thin, "solar_cell")
        parts += place(shade, rotation_about(_X, 90),
                       (0, -bus_r * 1.05, shade_h / 2 - bus_h / 2))
        parts.append(Part("sunshield_strut", "aluminium",
                          P.box((0.1, bus_r * 0.2, 0.1), (0, -bus_r * 0.95, 0))))
    else:  # Planck / Gaia: a wide round sunshield skirt below the bus
        skirt_r = bus_r * rng.uniform(1.8, 3.2)
        parts.append(Part("sunshield", "solar_cell",
                          P.transform_solid(P.prism(int(_pick(rng, (6, 12, 32))), skirt_r, thin),
                                            None, (0, 0, -bus_h / 2 - thin / 2 + 0.001))))
    parts += place(P.star_tracker(0.35), None, (bus_r * 0.7, 0, bus_h / 2 + 0.2))
    return parts


def comet_probe(rng: np.random.Generator, thin: float) -> list[Part]:
    """Box bus, two very long multi-panel wings and a side-mounted large dish
    (Rosetta, Dawn)."""
    bx, by, bz = rng.uniform(1.4, 2.6), rng.uniform(1.4, 2.6), rng.uniform(1.4, 3.2)
    parts = P.box_bus((bx, by, bz), _pick(rng, MLI))
    span, chord = rng.uniform(6.0, 16.0), rng.uniform(1.6, 3.6)
    parts += P.wing_pair(span, chord, int(rng.integers(3, 7)), thin, bx / 2,
                         yoke=rng.uniform(0.6, 1.5), cant_deg=rng.uniform(-50, 50))
    dish_d = rng.uniform(1.2, 3.2)
    facing = _pick(rng, ((0, 1, 0.2), (0, 0.3, 1), (0, 1, -0.4)))
    at = (0, 0, bz / 2) if facing[2] == 1 else (0, by / 2, 0)
    parts += _dish_on(rng, thin, dish_d, at, facing, mast=rng.uniform(0.1, 0.8))
    for k in range(int(rng.integers(1, 4))):
        parts += place(P.instrument_box((0.5, 0.4, 0.4), "silver_mli"), None,
                       (-bx / 4 + k * 0.4, -by / 4, bz / 2 + 0.2))
    if rng.random() < 0.5:  # Rosetta's lander on the far face
        parts += place(P.box_bus((0.9, 0.9, 0.6), "gold_mli"), None, (0, -by / 2 - 0.3, 0))
    parts += place(P.thruster_nozzle(0.5, 0.2), None, (0, 0, -bz / 2))
    return parts


def truss_science(rng: np.random.Generator, thin: float) -> list[Part]:
    """A long lattice truss carrying instruments at both ends, a small bus, masts and a wing
    (space stations' science payloads, gravity and plasma missions)."""
    length, width = rng.uniform(6.0, 12.0), rng.uniform(0.5, 1.0)
    parts = place(P.truss(length, width, 0.05, int(rng.integers(4, 9))), None,
                  (-length / 2, 0, 0))
    bus = rng.uniform(1.0, 1.6, size=3)
    parts += P.box_bus(bus, _pick(rng, MLI))
    for sign in (1, -1):
        s = rng.uniform(0.5, 1.2, size=3)
        parts += place(P.instrument_box(s, _pick(rng, ("white_paint", "gold_mli"))), None,
                       (sign * (length / 2 + s[0] / 2 - 0.05), 0, 0))
    wing = P.solar_wing(rng.uniform(3.0, 6.0), rng.uniform(1.0, 2.0), int(rng.integers(2, 5)),
                        thin, yoke=0.4)
    parts += place(wing, rotation_about(_Z, 90), (0, bus[1] / 2, 0))
    for k in range(int(rng.integers(1, 4))):
        a = rotation_about(_Z, -90 + 30 * (k - 1))
        parts += place(P.magnetometer_mast(rng.uniform(2.0, 5.0), 0.04),
                       a @ rotation_about(_Y, -20), (0, -bus[1] / 2, 0))
    return parts


def box_deployables(rng: np.random.Generator, thin: float) -> list[Part]:
    """A box bus with many deployables: two wings, several dishes and horns, booms and
    star trackers (large GEO and science platforms)."""
    bx, by, bz = rng.uniform(1.8, 2.8), rng.uniform(1.8, 2.8), rng.uniform(2.0, 3.5)
    parts = P.box_bus((bx, by, bz), _pick(rng, MLI))
    parts += P.wing_pair(rng.uniform(4.0, 8.0), rng.uniform(1.5, 2.5), int(rng.integers(2, 5)),
                         thin, bx / 2, yoke=0.6)
    for sign in (1, -1):
        parts += place(P.parabolic_dish(rng.uniform(1.5, 2.8), 0.35, thin),
                       P.frame_z_to((0, sign, 0.1)), (0, sign * by / 2, bz * 0.2))
    for k in range(int(rng.integers(2, 5))):
        parts += place(P.horn_antenna(rng.uniform(0.3, 0.7), rng.uniform(0.2, 0.4),
                                      pyramidal=bool(rng.random() < 0.6)),
                       None, (-bx / 3 + k * bx / 5, rng.uniform(-by / 4, by / 4), bz / 2))
    parts += place(P.boom(rng.uniform(1.5, 3.0), 0.04), rotation_about(_Y, -45),
                   (bx / 2, 0, bz / 2 - 0.1))
    for k in range(2):
        parts += place(P.star_tracker(0.3), P.frame_z_to((0.5 - k, 0, 1)),
                       (-bx / 3 + k * 0.6, -by / 3, bz / 2))
    parts += place(P.thruster_nozzle(0.6, 0.3), None, (0, 0, -bz / 2))
    return parts


def body_mounted(rng: np.random.Generator, thin: float) -> list[Part]:
    """A prism or box bus covered in body-mounted cells, with whip antennas and small
    deployables (early satellites, microsatellites, SMART-1-like probes)."""
    if rng.random() < 0.5:
        sides = int(_pick(rng, (6, 8)))
        radius, height = rng.uniform(0.5, 1.0), rng.uniform(0.6, 1.4)
        parts = P.prism_bus(sides, radius, height, "aluminium")
        apothem = radius * np.cos(np.pi / sides)
        width = 2 * radius * np.sin(np.pi / sides) * 0.92
        for k in range(sides):
            a = rotation_about(_Z, 360 * k / sides)
            plate = P.box((thin, width, height * 0.9), (apothem + thin / 4, 0, 0))
            parts.append(Part("body_cells", "solar_cell", P.transform_solid(plate, a)))
        top = height / 2
    else:
        size = rng.uniform(0.6, 1.4, size=3)
        parts = P.box_bus(size, "aluminium")
        parts += P.body_cells(size, thin, ("+x", "-x", "+y", "-y", "+z"), margin=0.03)
        radius, top = float(min(size[:2]) / 2), size[2] / 2
    for k in range(4):
        direction = rotation_about(_Z, 90 * k + 45) @ np.array([0.6, 0, 0.8])
        root = np.array([0, 0, top]) + rotation_about(_Z, 90 * k + 45) @ np.array(
            [radius * 0.5, 0, 0])
        parts.append(Part("whip_antenna", "aluminium",
                          P.rod(root, root + direction * rng.uniform(0.8, 2.0), 0.015, 6)))
    if rng.random() < 0.6:
        parts += place(P.horn_antenna(0.3, 0.25), P.frame_z_to((0, 0, -1)), (0, 0, -top))
    if rng.random() < 0.5:
        parts += place(P.magnetometer_mast(rng.uniform(1.5, 3.0), 0.03), None, (radius, 0, 0))
    return parts


def asteroid_sampler(rng: np.random.Generator, thin: float) -> list[Part]:
    """Box bus with two wings canted back, a sampling arm and a top dish
    (OSIRIS-REx, Hayabusa, Lucy-like probes)."""
    bx, by, bz = rng.uniform(1.6, 2.4), rng.uniform(1.6, 2.4), rng.uniform(1.6, 2.6)
    parts = P.box_bus((bx, by, bz), _pick(rng, MLI))
    cant = rng.uniform(15, 45)
    wing = P.solar_wing(rng.uniform(2.5, 5.5), rng.uniform(1.5, 2.4), int(rng.integers(1, 4)),
                        thin, yoke=0.4)
    for sign in (1, -1):
        tilted = place(wing, rotation_about(_Y, cant))
        parts += place(tilted, rotation_about(_Z, 0 if sign > 0 else 180),
                       (sign * bx / 2, 0, -bz / 4))
    parts += _dish_on(rng, thin, rng.uniform(1.5, 2.2), (0, 0, bz / 2), _Z, 0.1)
    arm_len = rng.uniform(2.0, 3.2)
    parts.append(Part("sampling_arm", "aluminium",
                      P.rod((bx / 4, 0, -bz / 2), (bx / 4, 0, -bz / 2 - arm_len), 0.05)))
    parts.append(Part("sampler_head", "aluminium",
                      P.transform_solid(P.prism(16, 0.15, 0.1), None,
                                        (bx / 4, 0, -bz / 2 - arm_len))))
    parts += place(P.instrument_box((0.5, 0.5, 0.4), "white_paint"), P.frame_z_to((0, 0, -1)),
                   (-bx / 4, by / 4, -bz / 2 - 0.2))
    return parts


ARCHETYPES: dict[str, Recipe] = {
    "twin_wing": twin_wing,
    "single_wing": single_wing,
    "tri_wing": tri_wing,
    "dish_probe": dish_probe,
    "telescope": telescope,
    "cubesat": cubesat,
    "solar_probe": solar_probe,
    "lander": lander,
    "sunshade_observatory": sunshade_observatory,
    "comet_probe": comet_probe,
    "truss_science": truss_science,
    "box_deployables": box_deployables,
    "body_mounted": body_mounted,
    "asteroid_sampler": asteroid_sampler,
}
