"""Archetype families: seeded recipes that assemble parts into spacecraft of a real class.

Each recipe takes a ``numpy.random.Generator`` and the thickness ``thin`` of thin parts
(panels, sunshields, dish shells) and returns the parts in the spacecraft's body frame.
Recipes draw all their random numbers from the generator in a fixed order, so the same
generator state gives the same spacecraft.

Convention: every spacecraft is one connected body. Each appendage overlaps the part it is
mounted on by a positive volume (see the attachment convention of
:mod:`sq_mitsuba.data.spacecraft.parts`), so the exact union of a recipe's parts is a single
watertight piece; ``tests/test_spacecraft.py`` checks this for every family.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from sq_mitsuba.data.spacecraft import parts as P
from sq_mitsuba.data.spacecraft.parts import Part, place, rotation_about

Recipe = Callable[[np.random.Generator, float], list[Part]]

_X, _Y, _Z = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)
MLI = ("gold_mli", "silver_mli")


def _pick(rng: np.random.Generator, options: tuple) -> object:
    return options[int(rng.integers(len(options)))]


def _dish_on(rng: np.random.Generator, thin: float, diameter: float, at: tuple,
             facing: tuple, mast: float = 0.0, embed: float = 0.1) -> list[Part]:
    """A dish on a mast at ``at`` (a point on a surface), opening towards ``facing``.

    The mast runs from ``embed`` behind ``at`` (inside the surface) through ``mast`` of free
    length into the dish's vertex, so dish, mast and mounting overlap.
    """
    depth = diameter * rng.uniform(0.12, 0.25)
    dish = P.parabolic_dish(diameter, depth, thin, feed=bool(rng.random() < 0.8))
    parts = place(dish, None, (0, 0, mast))
    mast_radius = max(0.025 * diameter, thin)
    parts += [Part("antenna_mast", "aluminium",
                   P.rod((0, 0, -embed), (0, 0, mast + 0.6 * thin), mast_radius))]
    return place(parts, P.frame_z_to(facing), at)


def _hang_below(parts: list[Part], height: float, at: tuple, overlap: float) -> list[Part]:
    """Parts built centred on the origin with their face on +z (``height`` tall) hung under
    a horizontal face at ``at`` (a point on it), facing down, sunk ``overlap`` into the face."""
    return place(parts, P.frame_z_to((0, 0, -1)),
                 (at[0], at[1], at[2] - height / 2 + overlap))


def twin_wing(rng: np.random.Generator, thin: float) -> list[Part]:
    """Box bus with two symmetric multi-panel wings (communications / Earth observation)."""
    bx, by, bz = rng.uniform(1.2, 2.2), rng.uniform(1.2, 2.2), rng.uniform(1.5, 3.0)
    parts = P.box_bus((bx, by, bz), _pick(rng, MLI))
    span, chord = rng.uniform(2.5, 6.0), rng.uniform(1.2, 2.2)
    panels = int(rng.integers(2, 6))
    parts += P.wing_pair(span, chord, panels, thin, bx / 2, yoke=rng.uniform(0.3, 1.0),
                         cant_deg=rng.uniform(-30, 30) if rng.random() < 0.4 else 0.0)
    parts += _dish_on(rng, thin, rng.uniform(0.8, 2.0), (0, 0, bz / 2), _Z,
                      mast=rng.uniform(0.0, 0.6))
    if rng.random() < 0.7:  # a second, side-looking dish on the +y face
        parts += _dish_on(rng, thin, rng.uniform(0.6, 1.4), (0, by / 2, bz * 0.3), (0, 1, 0.3),
                          mast=rng.uniform(0.2, 0.5))
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
    for _ in range(int(rng.integers(2, 5))):  # nadir instruments under the bus
        s = rng.uniform(0.4, 1.0, size=3)
        at = (rng.uniform(-bx / 3, bx / 3), rng.uniform(-by / 3, by / 3), -bz / 2)
        parts += _hang_below(P.instrument_box(s, _pick(rng, ("white_paint", "silver_mli"))),
                             s[2], at, overlap=0.05)
    parts += place(P.star_tracker(0.25), None, (-bx / 4, by / 4, bz / 2))
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
    cant = rng.uniform(-25, 25) if rng.random() < 0.5 else 0.0  # cells turned about the wing
    dihedral = rotation_about(_Y, -rng.uniform(-12, 12))  # wings raised or lowered
    for k in range(3):
        wing = place(P.solar_wing(span, chord, panels, thin, yoke=0.4, cant_deg=cant), dihedral)
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
    bottom = -bus_h / 2
    if rng.random() < 0.5:  # Cassini-like tall propulsion stack below the bus
        tank_h = rng.uniform(2.0, 4.0)
        parts += place(P.prism_bus(P.CIRCLE_SEGMENTS, bus_r * 0.8, tank_h, "gold_mli"), None,
                       (0, 0, bottom - tank_h / 2 + 0.1))
        bottom -= tank_h - 0.1
        parts += place(P.thruster_nozzle(0.8, 0.4), None, (0, 0, bottom))
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
    overlap = 0.1
    parts += place(P.prism_bus(int(_pick(rng, (8, 32))), radius * 1.1, aft_len,
                               _pick(rng, MLI)), None, (0, 0, -aft_len / 2 + overlap))
    span, chord = rng.uniform(4.0, 9.0), rng.uniform(1.8, 3.0)
    wing = P.solar_wing(span, chord, int(rng.integers(1, 4)), thin, yoke=0.4,
                        cant_deg=90.0 * (rng.random() < 0.5))
    z_wing = length * rng.uniform(0.15, 0.45)
    parts += place(wing, None, (radius * 0.95, 0, z_wing))
    parts += place(wing, rotation_about(_Z, 180), (-radius * 0.95, 0, z_wing))
    for sign in (1, -1):  # high-gain antennas on masts either side of the tube
        parts += _dish_on(rng, thin, rng.uniform(0.7, 1.2), (0, sign * radius * 0.95,
                                                             length * 0.3),
                          (0, sign, 0), mast=1.0 + 0.05 * radius)
    parts += place(P.star_tracker(0.4), P.frame_z_to((0, 0, -1)),
                   (radius * 0.6, radius * 0.5, -aft_len + overlap))
    return parts


def cubesat(rng: np.random.Generator, thin: float) -> list[Part]:
    """A 1U-12U CubeSat with body cells and optional deployable panels and whip antennas."""
    units = int(_pick(rng, (1, 2, 3, 3, 6, 6, 12)))
    size = np.array(P.CUBESAT_UNITS[units], float) * P.CUBESAT_UNIT_M
    body = P.cubesat_body_size(units)
    parts = P.cubesat_bus(units, thin)
    style = int(rng.integers(3))
    yoke_r = 0.006
    if style > 0:  # panels hinged just inside the top (+z) edge of the +-x and +-y faces
        faces = (0, 1, 2, 3) if style == 2 else (0, 2)
        for k in faces:
            angle = 90 * k
            half = body[0] / 2 if k % 2 == 0 else body[1] / 2
            width = 0.9 * (body[1] if k % 2 == 0 else body[0])  # clear of the rails
            n = int(rng.integers(1, 4))
            wing = P.solar_wing(size[2] * n, width, n, thin, yoke=0.02, gap=0.005,
                                yoke_radius=yoke_r, embed=2 * yoke_r)
            tilt = rotation_about(_Y, -rng.uniform(0, 60))
            root = np.array([half - yoke_r, 0, size[2] / 2 - 2 * yoke_r])
            parts += place(place(wing, tilt), rotation_about(_Z, angle),
                           rotation_about(_Z, angle) @ root)
    for k in range(int(rng.integers(0, 5))):  # tape-measure whips out of the side faces
        radial = rotation_about(_Z, 90 * k) @ np.array([1.0, 0, 0])
        droop = np.radians(rng.uniform(0, 15))
        direction = np.cos(droop) * radial + np.array([0, 0, -np.sin(droop)])
        root = np.array([0, 0, -size[2] / 2 + 0.01])
        parts.append(Part("whip_antenna", "aluminium",
                          P.rod(root, root + direction * (min(body[:2]) / 2 + rng.uniform(
                              0.15, 0.5)), 0.003, 6)))
    if units >= 6 and rng.random() < 0.5:
        parts += _dish_on(rng, thin, size[0] * 0.9, (0, 0, size[2] / 2), _Z, mast=0.01,
                          embed=0.01)
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
        p0 = a @ np.array([bus_r * 0.6, 0, bus_h / 2 - 0.05])
        p1 = a @ np.array([bus_r * 0.9, 0, bus_h / 2 + gap])
        parts.append(Part("truss", "dark_composite", P.rod(p0, p1, 0.03, 6)))
    span, chord = rng.uniform(1.0, 1.8), rng.uniform(0.6, 0.9)
    cant = rng.uniform(20, 70)
    for sign in (1, -1):
        wing = P.solar_wing(span, chord, 1, thin, yoke=0.3, cant_deg=sign * cant)
        wing = place(wing, rotation_about(_Y, -rng.uniform(10, 40)))
        parts += place(wing, rotation_about(_Z, 0 if sign > 0 else 180),
                       (sign * bus_r * 0.9, 0, -bus_h / 4))
    parts += _dish_on(rng, thin, rng.uniform(0.5, 0.8), (0, -bus_r * 0.9, -bus_h / 2),
                      (0, -1, -0.5), mast=0.1)
    parts += place(P.magnetometer_mast(rng.uniform(2.0, 3.5), 0.03),  # down, in the shade
                   rotation_about(_Y, 90), (0, 0, -bus_h / 2))
    return parts


def lander(rng: np.random.Generator, thin: float) -> list[Part]:
    """Hexagonal or octagonal deck on three or four legs, round-ish wings, descent engines
    (Phoenix, InSight, Surveyor)."""
    sides = int(_pick(rng, (6, 8)))
    deck_r, deck_h = rng.uniform(0.6, 1.3), rng.uniform(0.3, 0.8)
    deck_apothem = deck_r * np.cos(np.pi / sides)
    top = deck_h / 2
    parts = P.prism_bus(sides, deck_r, deck_h, _pick(rng, ("white_paint", "gold_mli")))
    legs = int(_pick(rng, (3, 4)))
    leg_h = rng.uniform(0.6, 1.0)
    for k in range(legs):
        a = rotation_about(_Z, 360 * k / legs + 30)
        parts += place(P.lander_leg(leg_h, rng.uniform(0.3, 0.6), 0.04), a,
                       a @ np.array([deck_r * 0.8, 0, -deck_h / 2 + 0.05]))
    # Square (Surveyor-like) or decagonal "round" (Phoenix-, InSight-like) wings on yokes
    # that reach from inside the deck 0.15 into the panel.
    wing_r = rng.uniform(0.6, 1.5)
    wing_sides = int(_pick(rng, (4, 10)))
    wing_apothem = wing_r * np.cos(np.pi / wing_sides)
    for sign in (1, -1):
        centre = deck_apothem + 0.15 + wing_apothem
        parts.append(Part("solar_panel", "solar_cell",
                          P.transform_solid(P.prism(wing_sides, wing_r, thin), None,
                                            (sign * centre, 0, top))))
        parts.append(Part("yoke", "aluminium",
                          P.box((0.45, 0.1, 0.06), (sign * (deck_apothem + 0.075), 0, top))))
    for k in range(int(rng.integers(3, 6))):
        a = rotation_about(_Z, 360 * k / 5 + 10)
        parts += place(P.thruster_nozzle(0.2, 0.08), None,
                       a @ np.array([deck_r * 0.4, 0, -deck_h / 2]))
    parts += place(P.instrument_box((0.25, 0.25, 0.25), "white_paint"), None,
                   (0, deck_r * 0.3, top + 0.1))
    arm = P.rod((0, 0, 0), (rng.uniform(1.0, 1.6), 0, rng.uniform(0.2, 0.6)), 0.03)
    parts.append(Part("robotic_arm", "aluminium",
                      P.transform_solid(arm, rotation_about(_Z, 90), (0, 0, top - 0.05))))
    if rng.random() < 0.7:  # camera mast
        parts += [Part("camera_mast", "aluminium",
                       P.rod((0, -deck_r * 0.5, top - 0.1), (0, -deck_r * 0.5, 1.4), 0.03))]
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
    parts += place(P.telescope_tube(tele_r, tele_h, thin, door=False), None,
                   (0, 0, bus_h / 2 - 0.1))
    if rng.random() < 0.5:  # Herschel: tall flat sunshade on one side, on struts
        shade_w, shade_h = bus_r * 2.2, bus_h + tele_h
        shade = P.sunshield(shade_w, shade_h, thin, "solar_cell")
        shade_y = -bus_r * 1.05
        parts += place(shade, rotation_about(_X, 90), (0, shade_y, shade_h / 2 - bus_h / 2))
        parts.append(Part("sunshield_strut", "aluminium",  # from inside the bus to the shade
                          P.box((0.1, bus_r * 0.25, 0.1), (0, shade_y + bus_r * 0.125, 0))))
        z_top = bus_h / 2 + tele_h * 0.75  # upper strut from the telescope tube
        for x in (-0.3 * tele_r, 0.3 * tele_r):
            parts.append(Part("sunshield_strut", "aluminium",
                              P.rod((x, -tele_r * 0.8, z_top), (x, shade_y, z_top), 0.04)))
    else:  # Planck / Gaia: a wide round sunshield skirt below the bus
        skirt_r = bus_r * rng.uniform(1.8, 3.2)
        parts.append(Part("sunshield", "solar_cell",
                          P.transform_solid(P.prism(int(_pick(rng, (6, 12, 32))), skirt_r, thin),
                                            None, (0, 0, -bus_h / 2))))
    parts += place(P.star_tracker(0.35), P.frame_z_to((1, 0, 0.4)), (bus_r * 0.85, 0, 0))
    return parts


def comet_probe(rng: np.random.Generator, thin: float) -> list[Part]:
    """Box bus, two very long multi-panel wings and a side-mounted large dish
    (Rosetta, Dawn)."""
    bx, by, bz = rng.uniform(1.4, 2.6), rng.uniform(1.4, 2.6), rng.uniform(1.4, 3.2)
    parts = P.box_bus((bx, by, bz), _pick(rng, MLI))
    span, chord = rng.uniform(8.0, 16.0), rng.uniform(1.6, 3.6)  # very long, like Rosetta
    parts += P.wing_pair(span, chord, int(rng.integers(3, 7)), thin, bx / 2,
                         yoke=rng.uniform(0.6, 1.5), cant_deg=rng.uniform(-50, 50))
    dish_d = rng.uniform(1.2, 3.2)
    facing = _pick(rng, ((0, 1, 0.2), (0, 0.3, 1), (0, 1, -0.4)))
    at = (0, 0, bz / 2) if facing[2] == 1 else (0, by / 2, 0)
    parts += _dish_on(rng, thin, dish_d, at, facing, mast=rng.uniform(0.1, 0.8))
    for k in range(int(rng.integers(1, 4))):  # instrument platform on the top face
        parts += place(P.instrument_box((0.5, 0.4, 0.4), "silver_mli"), None,
                       (-bx / 4 + k * 0.4, -by / 4, bz / 2 + 0.15))
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
    for sign in (1, -1):  # end instruments, wider than the truss so its end frame sinks in
        s = rng.uniform(0.5, 1.2, size=3)
        s[1:] = np.maximum(s[1:], width + 0.15)
        parts += place(P.instrument_box(s, _pick(rng, ("white_paint", "gold_mli"))), None,
                       (sign * (length / 2 + s[0] / 2 - 0.1), 0, 0))
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
                         thin, bx / 2, yoke=rng.uniform(0.4, 1.2),
                         cant_deg=rng.uniform(-45, 45))  # wings turned towards the sun
    for sign in (1, -1):  # east and west reflectors
        parts += _dish_on(rng, thin, rng.uniform(1.2, 2.4), (0, sign * by / 2, bz * 0.2),
                          (0, sign, 0.1), mast=rng.uniform(0.2, 0.5))
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
    for k in range(4):  # whips rising from just inside the top face
        direction = rotation_about(_Z, 90 * k + 45) @ np.array([0.6, 0, 0.8])
        root = np.array([0, 0, top - 0.05]) + rotation_about(_Z, 90 * k + 45) @ np.array(
            [radius * 0.5, 0, 0])
        parts.append(Part("whip_antenna", "aluminium",
                          P.rod(root, root + direction * rng.uniform(0.8, 2.0), 0.015, 6)))
    if rng.random() < 0.6:
        parts += place(P.horn_antenna(0.3, 0.25), P.frame_z_to((0, 0, -1)), (0, 0, -top))
    if rng.random() < 0.5:
        parts += place(P.magnetometer_mast(rng.uniform(1.5, 3.0), 0.03, embed=0.0), None,
                       (radius * 0.5, 0, 0))
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
                      P.rod((bx / 4, 0, -bz / 2 + 0.1), (bx / 4, 0, -bz / 2 - arm_len), 0.05)))
    parts.append(Part("sampler_head", "aluminium",
                      P.transform_solid(P.prism(16, 0.15, 0.1), None,
                                        (bx / 4, 0, -bz / 2 - arm_len))))
    parts += _hang_below(P.instrument_box((0.5, 0.5, 0.4), "white_paint"), 0.4,
                         (-bx / 4, by / 4, -bz / 2), overlap=0.05)
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
