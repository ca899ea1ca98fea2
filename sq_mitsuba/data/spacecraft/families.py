"""Spacecraft families of the compositional generator, and the fixed leave-family-out set.

Each family is a recipe composed from the attachment grammar
(:mod:`sq_mitsuba.data.spacecraft.grammar`) and the parts library: it draws a bus, then
which appendages to attach, how many, where and at what angles, with proportions spread
over the range of the real class (arrays 2-14 times the bus, booms and masts longer than the
body, one to four dishes, canted and off-axis attachments, asymmetric layouts). Same
conventions as :mod:`sq_mitsuba.data.spacecraft.archetypes`: a recipe takes ``(rng, thin)``
and returns the parts in the body frame, draws all its random numbers from ``rng`` in a
fixed order (same seed, same spacecraft), and builds one connected body (every appendage
overlaps what it is mounted on by a positive volume).

:data:`FAMILIES` names the recipes; :data:`HELD_OUT_FAMILIES` is the fixed set of families
never trained on (see its docstring).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from sq_mitsuba.data.spacecraft import grammar as G
from sq_mitsuba.data.spacecraft import parts as P
from sq_mitsuba.data.spacecraft.grammar import BUS_MATERIALS, MLI, X, Y, Z, chance, pick
from sq_mitsuba.data.spacecraft.parts import Part, place, rotation_about

Recipe = Callable[[np.random.Generator, float], list[Part]]

_PRISM_SIDES = {"tri": 3, "hex": 6, "oct": 8, "dec": 10, "cyl": 32}


def _bus(shape: str, size: np.ndarray, material: str, axis=Z) -> G.Body:
    """A bus host: ``"box"`` of ``size``, or a prism (``tri``, ``hex``, ``oct``, ``dec``,
    ``cyl``) along ``axis`` of diameter ``max(size[:2])`` and height ``size[2]``."""
    rotation = G.orient(Z, axis, X, Z) if abs(G.unit(axis) @ Z) < 0.99 else None
    if shape == "box":
        return G.box_body(size, material, rotation=rotation)
    return G.prism_body(_PRISM_SIDES[shape], float(max(size[0], size[1])) / 2, float(size[2]),
                        material, rotation=rotation)


def _recolour(parts: list[Part], kind: str, material: str, of: str = "solar_panel",
              ) -> list[Part]:
    """Parts of kind ``of`` renamed ``kind`` in ``material`` (a wing built as a radiator)."""
    return [Part(kind, material, p.solid) if p.kind == of else p for p in parts]


def _star_trackers(rng: np.random.Generator, body: G.Body, face_dir, count: int,
                   size: float) -> list[Part]:
    """``count`` star trackers on the face towards ``face_dir``, looking off-axis."""
    parts: list[Part] = []
    for _ in range(count):
        shift = rng.uniform(-0.35, 0.35, size=3) * body.size
        site = body.toward(face_dir, body.rotation @ shift)
        look = G.tilted(rng, site.normal, 50, 15)
        parts += G.mount(P.star_tracker(size), site, Z, look)
    return parts


def _instruments(rng: np.random.Generator, body: G.Body, face_dir, count: int, scale: float,
                 ) -> list[Part]:
    """``count`` instruments (boxes with apertures, telescopes, scanners) on the face of
    ``body`` towards ``face_dir``, some looking off the face's normal."""
    parts: list[Part] = []
    for _ in range(count):
        shift = rng.uniform(-0.38, 0.38, size=3) * body.size
        site = body.toward(face_dir, body.rotation @ shift)
        kind = pick(rng, ("box", "box", "tube", "scanner"))
        s = scale * rng.uniform(0.35, 1.0, size=3)
        material = pick(rng, ("white_paint", "silver_mli", "gold_mli", "aluminium"))
        look = G.tilted(rng, site.normal, 35)
        if kind == "box":
            parts += G.box_on(site, s, material, aperture=True, up=G.perpendicular(look))
        elif kind == "tube":
            parts += G.mount(P.telescope_tube(s[0] * 0.4, s[2] * 1.6, 0.02 * scale, door=False),
                             site, Z, look, lift=-site.embed(cap=0.2 * s[2]))
        else:
            parts += G.cylinder_on(site, s[0] * 0.5, s[2] * 0.8, material, "instrument",
                                   direction=look)
    return parts


def _radiators(rng: np.random.Generator, body: G.Body, thin: float, count: int,
               scale: float) -> list[Part]:
    """``count`` radiator panels standing off the bus on struts, tilted off its faces."""
    parts: list[Part] = []
    for _ in range(count):
        direction = G.unit(rng.normal(size=3))
        site = body.toward(direction)
        out = G.tilted(rng, site.normal, 30)
        standoff = scale * rng.uniform(0.1, 0.6)
        strut, tip = G.boom_from(site, out, standoff, G.rod_radius(0.04 * scale, thin),
                                 "radiator_strut")
        w, h = scale * rng.uniform(0.8, 2.2), scale * rng.uniform(0.6, 1.8)
        panel = P.flat_panel("radiator", "white_paint", w, h, 1.5 * thin)
        parts += strut + G.mount(panel, tip, Z, G.tilted(rng, out, 25), X,
                                 G.perpendicular(out))
    return parts


def _magnetometer(site: G.Site, direction, length: float, thin: float, radius: float = 0.03,
                  ) -> list[Part]:
    """A magnetometer mast from ``site`` along ``direction``, sensors half way and at tip."""
    r = G.rod_radius(radius, thin)
    local = P.magnetometer_mast(length, r, embed=site.embed(cap=max(0.1, 3 * r)))
    return G.mount(local, site, X, direction)


# ------------------------------------------------------------------------------ families

def earth_observer(rng: np.random.Generator, thin: float) -> list[Part]:
    """Earth observers (Landsat, Sentinel-1/2/3, Terra, Aqua, SPOT, JPSS, GOES-R): ONE large
    single-sided array on a side or an end of the bus, often canted and off the face's
    normal; an instrument-laden nadir deck (boxes, telescopes, scanners); radiators on struts;
    a side-looking radar antenna (Sentinel-1), a data-downlink dish, a magnetometer boom.
    Varies: bus shape and aspect, array span 1.3-3.5 x the bus length, where and at what angle
    the array stands, instrument count and kinds, optional radar and boom."""
    shape = pick(rng, ("box", "box", "box", "hex", "oct"))
    size = np.array([rng.uniform(1.3, 2.6), rng.uniform(1.3, 2.6), rng.uniform(2.0, 6.5)])
    bus = _bus(shape, size, pick(rng, BUS_MATERIALS), axis=X)  # long axis along flight (x)
    parts = list(bus.parts)
    length = size[2]
    # The single array: on a side (+y) or at the aft end (-x), leaning off the face's normal.
    where = pick(rng, ("side", "side", "aft", "top_edge"))
    shift = np.array([rng.uniform(-0.35, 0.35) * length, 0, rng.uniform(-0.3, 0.3) * size[1]])
    site = bus.toward({"side": Y, "aft": -X, "top_edge": G.unit((0, 1, 1))}[where], shift)
    out = G.turned(site.normal, pick(rng, (X, -X, Z, -Z)), rng.uniform(0, 40))
    span = rng.uniform(1.3, 3.5) * length
    chord = rng.uniform(0.35, 0.8) * span / rng.uniform(2.0, 4.0)
    style = pick(rng, ("rect", "rect", "rect", "double", "rollout"))
    sun = G.turned(Z, Y, rng.uniform(-70, 70))
    array = G.wing(rng, style, span, min(chord, 4.5), int(rng.integers(3, 9)), thin,
                   yoke=rng.uniform(0.3, 2.5), embed=site.embed(cap=0.4))
    parts += G.wing_at(site, out, sun, array)
    if chance(rng, 0.3):  # a side-looking radar antenna on the other side (Sentinel-1)
        site = bus.toward(-Y)
        sar_len = length * rng.uniform(1.5, 3.5)
        look = G.turned(-Y, -Z, rng.uniform(15, 45))
        strut, tip = G.boom_from(site, -Y, rng.uniform(0.2, 0.8), G.rod_radius(0.08, thin),
                                 "antenna_strut")
        panel = P.flat_panel("sar_antenna", pick(rng, ("antenna_white", "dark_composite")),
                             sar_len, rng.uniform(0.7, 1.5), 2.5 * thin)
        parts += strut + G.mount(panel, tip, Z, look, X, X)
    scale = float(np.sqrt(size[0] * size[1]))
    parts += _instruments(rng, bus, -Z, int(rng.integers(2, 7)), 0.6 * scale)
    parts += _radiators(rng, bus, thin, int(rng.integers(0, 3)), 0.8 * scale)
    if chance(rng, 0.7):  # downlink dish on a mast, tilted
        site = bus.toward(-Z, (rng.uniform(-0.4, 0.4) * length, 0, 0))
        parts += G.dish_at(rng, site, rng.uniform(0.4, 1.1), thin, G.tilted(rng, -Z, 40),
                           mast=rng.uniform(0.2, 1.2))
    if chance(rng, 0.3):  # magnetometer boom (GOES-R, Swarm)
        site = bus.toward(pick(rng, (X, -X, Z)))
        parts += _magnetometer(site, G.tilted(rng, site.normal, 35),
                               length * rng.uniform(0.8, 2.0), thin)
    parts += _star_trackers(rng, bus, Z, int(rng.integers(1, 4)), 0.25)
    return parts


def comms_relay(rng: np.random.Generator, thin: float) -> list[Part]:
    """Communication, relay and navigation satellites (Intelsat, SES, Eutelsat, Inmarsat,
    ViaSat, TDRS, GPS, Galileo): a tall box bus (sometimes with a stacked antenna module),
    long twin arrays on the north and south faces, one to four large dishes - reflectors on
    arms at the east and west faces, dishes on the Earth deck, TDRS-like huge dishes on
    booms - horns, or a navigation antenna panel. Varies: array span 1.5-5 x the bus per wing
    and its style, cant and yoke; dish count, size, arms and tilts; the stack."""
    size = np.array([rng.uniform(1.8, 3.2), rng.uniform(1.8, 3.0), rng.uniform(2.0, 5.5)])
    bus = G.box_body(size, pick(rng, BUS_MATERIALS))
    parts = list(bus.parts)
    deck = bus
    if chance(rng, 0.3):  # an antenna module stacked on the Earth deck
        deck = G.stacked_on(bus, rng.uniform(0.6, 1.6), rng.uniform(0.6, 0.9),
                            pick(rng, BUS_MATERIALS))
        parts += deck.parts
    style = pick(rng, ("rect", "rect", "rect", "double", "rollout"))
    span = size[1] * rng.uniform(1.5, 5.0)
    chord = rng.uniform(1.6, 2.9)
    parts += G.wing_pair_at(bus, rng, style, span, chord, int(rng.integers(3, 7)), thin, Y,
                            G.turned(Z, X, rng.uniform(-50, 50)), yoke=rng.uniform(0.6, 2.5),
                            cant_deg=rng.uniform(-15, 15), height=rng.uniform(-0.3, 0.3))
    layout = pick(rng, ("reflectors", "reflectors", "tdrs", "deck", "nav"))
    n_dishes = int(pick(rng, (1, 2, 2, 2, 3, 3, 4)))
    slots = []  # (site, arm direction, arm length, facing, diameter)
    for k in range(n_dishes):
        side = X if k % 2 == 0 else -X
        if (layout == "reflectors" and k < 2) or (layout == "deck" and k >= 2):
            site = bus.toward(side, (0, 0, size[2] * rng.uniform(0.1, 0.45)))
            arm = G.turned(side, Z, rng.uniform(10, 60))
            facing = G.turned(Z, side, rng.uniform(10, 45))
            slots.append((site, arm, rng.uniform(0.3, 1.6), facing, rng.uniform(2.2, 4.2)))
        elif layout == "tdrs" and k < 2:
            site = deck.toward(Z, (0.3 * side[0] * size[0], 0, 0))
            arm = G.turned(side, Z, rng.uniform(20, 60))
            facing = G.turned(Z, side, rng.uniform(0, 40))
            slots.append((site, arm, rng.uniform(1.5, 3.5), facing, rng.uniform(3.5, 5.0)))
        else:  # on the Earth deck
            u, v = rng.uniform(-0.6, 0.6, size=2)
            site = deck.face("+z", u, v)
            slots.append((site, G.tilted(rng, Z, 20), rng.uniform(0.0, 0.6),
                          G.tilted(rng, Z, 30), rng.uniform(0.7, 2.0)))
    for site, arm, arm_len, facing, diameter in slots:
        r = G.rod_radius(0.06, thin)
        boom, tip = G.boom_from(site, arm, arm_len, r, "antenna_arm")
        block = G.tip_block(tip, 3 * r)
        parts += boom + block.parts
        parts += G.dish_at(rng, block.toward(facing), diameter, thin, facing, mast=0.1)
    if layout == "nav":  # a navigation antenna panel with helices on the Earth deck
        top = deck.face("+z")
        w = 0.8 * min(deck.size[0], deck.size[1])
        parts += G.box_on(top, (w, w, 0.15), "white_paint", "antenna_panel")
        count = int(rng.integers(4, 13))
        for k in range(count):
            a = 2 * np.pi * k / count
            site = top.offset((0.3 * w * np.cos(a), 0.3 * w * np.sin(a), 0.1))
            parts += G.cylinder_on(site, 0.06, rng.uniform(0.3, 0.7), "aluminium",
                                   "helix_antenna", sink=0.1, sides=8)
    for _ in range(int(rng.integers(0, 5))):  # horns on the Earth deck
        u, v = rng.uniform(-0.8, 0.8, size=2)
        parts += G.mount(P.horn_antenna(rng.uniform(0.3, 0.7), rng.uniform(0.2, 0.45),
                                        pyramidal=chance(rng, 0.6)),
                         deck.face("+z", u, v), Z, G.tilted(rng, Z, 25))
    parts += place(P.thruster_nozzle(0.6, 0.3), None, bus.face("-z").point)
    return parts


def deep_space_probe(rng: np.random.Generator, thin: float) -> list[Part]:
    """Outer-planet and deep-space probes (Voyager, Pioneer, Galileo, Cassini, New Horizons,
    Ulysses): a high-gain dish one to three times the bus across, one to three finned RTGs -
    all on one boom, on separate booms, or on the bus - an instrument boom with a scan
    platform, magnetometer masts several times the body long and wire antennas, all at
    off-axis angles; sometimes a tall propulsion stack. Varies: bus shape (decagon, triangle,
    hexagon, box), dish size and mount, RTG count and layout, boom and mast lengths."""
    shape = pick(rng, ("dec", "dec", "tri", "hex", "box"))
    r, h = rng.uniform(0.5, 1.1), rng.uniform(0.4, 1.2)
    size = np.array([2 * r, 2 * r * rng.uniform(0.7, 1.0), h])
    bus = _bus(shape, size, pick(rng, ("aluminium", "gold_mli", "silver_mli")))
    parts = list(bus.parts)
    body = float(max(size))
    dish_d = 2 * r * rng.uniform(1.4, 2.6)
    top = bus.face("+z")
    if chance(rng, 0.75):
        parts += G.dish_at(rng, top, dish_d, thin, Z, mast=rng.uniform(0.05, 0.6))
    else:  # side-looking dish (Ulysses, Pioneer-like side mount)
        site = bus.side(rng.uniform(0, 360))
        parts += G.dish_at(rng, site, dish_d * 0.8, thin, G.turned(site.normal, Z, 30),
                           mast=rng.uniform(0.1, 0.5))
    if chance(rng, 0.35):  # Cassini-like propulsion stack below
        stack_h = rng.uniform(1.5, 3.5)
        stack = G.prism_body(32, r * 0.75, stack_h, "gold_mli",
                             center=(0, 0, -h / 2 - stack_h / 2 + 0.1))
        parts += stack.parts + place(P.thruster_nozzle(0.7, 0.35), None,
                                     stack.face("-z").point)
    n_rtg = int(pick(rng, (1, 2, 3, 3)))
    layout = pick(rng, ("one_boom", "split", "body"))
    azimuth = rng.uniform(0, 360)
    rtg_len, rtg_r = rng.uniform(0.8, 1.4), rng.uniform(0.15, 0.25)
    if layout == "one_boom":  # Voyager: RTGs in a row along one boom
        site = bus.side(azimuth)
        out = G.turned(site.normal, Z, rng.uniform(-20, 20))
        length = rng.uniform(1.5, 3.5) + n_rtg * rtg_len
        boom, _tip = G.boom_from(site, out, length, G.rod_radius(0.05, thin))
        parts += boom
        for k in range(n_rtg):
            centre = site.point + out * (length - (k + 0.5) * rtg_len * 1.02)
            parts += place(P.rtg(rtg_len, rtg_r), G.orient(Z, out), centre)
    else:
        for k in range(n_rtg):
            a = azimuth + 360 * k / n_rtg + rng.uniform(-25, 25)
            site = bus.side(a, rng.uniform(-0.8, 0.8))
            if layout == "split":
                out = G.turned(site.normal, -Z, rng.uniform(-10, 40))
                boom, tip = G.boom_from(site, out, rng.uniform(0.6, 2.5),
                                        G.rod_radius(0.05, thin))
                parts += boom + place(P.rtg(rtg_len, rtg_r), G.orient(Z, out),
                                      tip.point + out * (rtg_len / 2 - 0.1))
            else:  # on the bus, axis along the bus or across (New Horizons, Ulysses)
                axis = pick(rng, (Z, G.perpendicular(site.normal)))
                centre = site.point + site.normal * (rtg_r * 2.0)
                parts += place(P.rtg(rtg_len, rtg_r), G.orient(Z, axis), centre)
                parts += [Part("rtg_mount", "aluminium",
                               P.rod(site.point - site.normal * 0.1, centre, rtg_r * 0.6))]
    if chance(rng, 0.6):  # instrument boom with a scan platform
        site = bus.side(azimuth + 180 + rng.uniform(-40, 40))
        out = G.turned(site.normal, Z, rng.uniform(-15, 30))
        boom, tip = G.boom_from(site, out, rng.uniform(1.2, 3.5), G.rod_radius(0.05, thin))
        block = G.tip_block(tip, 0.5, "silver_mli", "scan_platform", up=Z,
                            shape=(rng.uniform(0.4, 0.9), rng.uniform(0.4, 0.9), 0.5))
        parts += boom + block.parts
        parts += _instruments(rng, block, -Z, int(rng.integers(1, 4)), 0.45)
    for k in range(int(pick(rng, (1, 1, 2)))):  # magnetometer masts, longer than the body
        site = bus.side(azimuth + 90 + 160 * k + rng.uniform(-30, 30), rng.uniform(-0.5, 0.5))
        out = G.turned(site.normal, pick(rng, (Z, -Z)), rng.uniform(0, 35))
        parts += _magnetometer(site, out, body * rng.uniform(2.5, 8.0), thin)
    for _ in range(int(rng.integers(0, 3))):  # plasma-wave wire antennas
        site = bus.side(rng.uniform(0, 360), -0.5)
        out = G.turned(site.normal, -Z, rng.uniform(20, 60))
        boom, _tip = G.boom_from(site, out, body * rng.uniform(2.0, 5.0),
                                 G.rod_radius(0.015, thin), "wire_antenna")
        parts += boom
    return parts


def sep_probe(rng: np.random.Generator, thin: float) -> list[Part]:
    """Solar-electric probes (Dawn, Psyche, Deep Space 1, SMART-1, Hayabusa2, Lucy, DART,
    BepiColombo's transfer module): very long arrays - rectangular wings, Psyche-like
    crosses, round UltraFlex discs (Lucy), roll-out blankets (DART) - one to three gimballed
    ion thrusters, a dish on a side face or on top, instruments or an instrument arm.
    Varies: tip-to-tip span 5-14 x the bus, array style, cant and dihedral, thruster count,
    dish size and place, bus shape."""
    shape = pick(rng, ("box", "box", "box", "cyl", "oct"))
    size = np.array([rng.uniform(1.1, 2.4), rng.uniform(1.1, 2.4), rng.uniform(1.1, 2.6)])
    bus = _bus(shape, size, pick(rng, BUS_MATERIALS))
    parts = list(bus.parts)
    body = float(max(size))
    style = pick(rng, ("rect", "rect", "cross", "circular", "rollout"))
    ratio = rng.uniform(5.0, 14.0)  # tip to tip over the bus
    yoke = rng.uniform(0.4, 1.5)
    wing_len = (ratio * body - 2 * yoke - (bus.size[1])) / 2
    if style == "circular":
        span, chord = min(wing_len, 4.5 * body), 0.0  # a disc of diameter span
    else:
        span, chord = wing_len, rng.uniform(1.2, 3.2)
    dihedral = rng.uniform(-12, 12) if chance(rng, 0.4) else 0.0
    cant = rng.uniform(-40, 40) if chance(rng, 0.5) else 0.0
    for k, side in enumerate((Y, -Y)):
        site = bus.toward(side)
        out = G.turned(side, Z, dihedral)
        local = G.wing(rng, style, span, chord, int(rng.integers(3, 7)), thin, yoke,
                       embed=site.embed(cap=0.4), cant_deg=cant if k == 0 else -cant)
        parts += G.wing_at(site, out, G.turned(Z, X, 0.0), local)
    n_thr = int(pick(rng, (1, 1, 2, 3)))
    bottom = bus.face("-z")
    for k in range(n_thr):
        offset = 0 if n_thr == 1 else 0.25 * float(min(bus.size[:2]))
        a = 2 * np.pi * k / n_thr
        site = bottom.offset((offset * np.cos(a), offset * np.sin(a), 0))
        parts += G.mount(P.ion_thruster(rng.uniform(0.15, 0.3), rng.uniform(0.2, 0.4)), site,
                         -Z, G.tilted(rng, -Z, 15), lift=0.0)
    if chance(rng, 0.5):  # dish on the +x side (Dawn) ...
        site = bus.toward(X, (0, 0, rng.uniform(-0.3, 0.3) * size[2]))
        facing = G.turned(X, Z, rng.uniform(-30, 40))
    else:  # ... or on top (Lucy)
        site = bus.face("+z")
        facing = G.tilted(rng, Z, 25)
    parts += G.dish_at(rng, site, body * rng.uniform(0.5, 1.3), thin, facing,
                       mast=rng.uniform(0.05, 0.5))
    if chance(rng, 0.35):  # instrument arm (Lucy's pointing platform)
        site = bus.toward(-X)
        boom, tip = G.boom_from(site, G.tilted(rng, -X, 40), rng.uniform(0.8, 2.5),
                                G.rod_radius(0.06, thin))
        block = G.tip_block(tip, 0.5, "gold_mli", "instrument_platform", up=Z)
        parts += boom + block.parts + _instruments(rng, block, Z, 2, 0.4)
    else:
        parts += _instruments(rng, bus, -X, int(rng.integers(1, 4)), 0.4 * body)
    parts += _star_trackers(rng, bus, Z, 2, 0.25)
    return parts


def smallsat(rng: np.random.Generator, thin: float) -> list[Part]:
    """Small satellites: CubeSats of 1-12 U with deployable panels (flower, T, one-sided,
    double-deployed), whips, tape-measure booms and reflectarrays (MarCO), and ESPA-class
    microsatellites with one to four panels, a gravity-gradient boom, a small dish.
    Varies: size, panel layout and angles, booms longer than the body."""
    if chance(rng, 0.6):
        return _cubesat(rng, thin)
    size = rng.uniform(0.4, 1.2, size=3)
    bus = G.box_body(size, pick(rng, ("aluminium", "gold_mli", "silver_mli", "white_paint")))
    parts = list(bus.parts) + P.body_cells(size, thin, ("+z", "-x", "+x"), margin=0.03)
    layout = pick(rng, ("one", "two", "two", "four"))
    n = {"one": 1, "two": 2, "four": 4}[layout]
    phase = rng.uniform(0, 90) if chance(rng, 0.4) else 0.0
    fold = rng.uniform(-30, 30)
    span = float(max(size)) * rng.uniform(1.0, 3.0)
    for k in range(n):
        site = bus.side(phase + 360 * k / n, rng.uniform(-0.5, 0.8))
        out = G.turned(site.normal, Z, fold)
        local = G.wing(rng, pick(rng, ("rect", "rect", "gull")), span,
                       float(min(size[:2])) * rng.uniform(0.6, 1.0), int(rng.integers(1, 4)),
                       thin, 0.05, embed=site.embed(cap=0.1))
        parts += G.wing_at(site, out, G.turned(Z, out, rng.uniform(-40, 40)), local)
    if chance(rng, 0.5):  # gravity-gradient boom with a tip mass, or magnetometer
        site = bus.toward(pick(rng, (Z, -Z, X)))
        boom, tip = G.boom_from(site, G.tilted(rng, site.normal, 30),
                                float(max(size)) * rng.uniform(1.5, 5.0),
                                G.rod_radius(0.015, thin))
        parts += boom + G.tip_block(tip, 0.12, "aluminium", "tip_mass").parts
    if chance(rng, 0.4):
        parts += G.dish_at(rng, bus.face("-z"), float(min(size[:2])) * 0.7, thin,
                           G.tilted(rng, -Z, 30), mast=0.05)
    for _ in range(int(rng.integers(0, 4))):
        site = bus.toward(G.unit(rng.normal(size=3)))
        boom, _tip = G.boom_from(site, G.tilted(rng, site.normal, 40),
                                 float(max(size)) * rng.uniform(0.5, 1.5),
                                 G.rod_radius(0.01, thin), "whip_antenna")
        parts += boom
    return parts


def _cubesat(rng: np.random.Generator, thin: float) -> list[Part]:
    units = int(pick(rng, (1, 2, 3, 3, 6, 6, 12)))
    size = np.array(P.CUBESAT_UNITS[units], float) * P.CUBESAT_UNIT_M
    body = P.cubesat_body_size(units)
    parts = P.cubesat_bus(units, thin)
    host = G.Body([], "box", body / 2)
    layout = pick(rng, ("none", "flower", "tee", "one_side", "double"))
    faces = {"none": (), "flower": (0, 90, 180, 270), "tee": (0, 180), "one_side": (0,),
             "double": (0, 180)}[layout]
    fold = rng.uniform(20, 100)
    n_panels = int(rng.integers(1, 4))
    for azimuth in faces:
        site = host.side(azimuth, 0.92)  # hinged near the top edge of a side face
        a = np.radians(azimuth)
        radial = np.array([np.cos(a), np.sin(a), 0.0])
        width = 0.85 * (body[1] if azimuth % 180 == 0 else body[0])
        tangent = np.cross(Z, radial)
        for hinge in ((1.0, -1.0) if layout == "double" else (1.0,)):
            along = G.turned(hinge * Z, radial, fold)
            local = G.wing(rng, "rect", size[2] * n_panels, width, n_panels, thin, 0.02,
                           embed=0.02)
            start = site.offset((0, 0, (hinge - 1) * 0.45 * body[2]))
            parts += G.wing_at(start, along, hinge * np.cross(tangent, along), local)
    for _ in range(int(rng.integers(0, 5))):  # tape-measure whips
        site = host.side(rng.uniform(0, 360), -0.9)
        boom, _tip = G.boom_from(site, G.turned(site.normal, -Z, rng.uniform(0, 20)),
                                 rng.uniform(0.15, 0.5), G.rod_radius(0.003, thin),
                                 "whip_antenna")
        parts += boom
    if chance(rng, 0.3):  # a magnetometer on a tape boom, several times the body
        site = host.face("-z")
        parts += _magnetometer(site, G.tilted(rng, -Z, 40), rng.uniform(0.5, 1.5), thin,
                               radius=0.004)
    if chance(rng, 0.25) and units >= 6:  # MarCO-like reflectarray on a hinge
        site = host.face("+z", 0.0, 0.9)
        panel = P.flat_panel("reflectarray", "antenna_white", size[0] * 0.95, size[2] * 0.9,
                             2 * thin)
        parts += G.mount(place(panel, None, (0, size[2] * 0.45 - 0.02, 0)), site, Z,
                         G.turned(Z, -Y, rng.uniform(0, 60)), Y, Y)
    return parts


def station_truss(rng: np.random.Generator, thin: float) -> list[Part]:
    """Truss-built stations (the International Space Station, truss-borne platforms): a long
    main truss carrying pairs of large arrays at its ends (double blankets or roll-outs,
    turned by their gimbals), radiators hanging off it, and a cluster of pressurised modules
    and nodes crossing it at the centre, with docked vehicles and small arrays on modules.
    Varies: truss length and width, array pairs per side (1-2), wing size and angle,
    radiators, the number, length and branching of modules."""
    length = rng.uniform(30.0, 100.0)
    width = rng.uniform(2.0, 4.5)
    mod_r = rng.uniform(1.8, 2.3)
    z_truss = mod_r + width / 2 + rng.uniform(0.5, 2.0)
    bays = int(np.clip(round(length / (width * 3)), 4, 12))
    parts = G.truss_between((-length / 2, 0, z_truss), (length / 2, 0, z_truss), width,
                            G.rod_radius(0.12, thin), bays)
    parts += G.box_body((width * 1.6, width * 1.6, z_truss), "aluminium", "truss_mount",
                        (0, 0, z_truss / 2)).parts
    # Arrays at both ends, on gimbal blocks: wings along +-y from each block.
    pairs = int(pick(rng, (1, 2, 2)))
    style = pick(rng, ("double", "double", "rollout", "rect"))
    span = rng.uniform(0.2, 0.45) * length
    chord = span * rng.uniform(0.18, 0.35)
    for sign in (1.0, -1.0):
        alpha = rng.uniform(-60, 60)  # the side's rotary joint
        for k in range(pairs):
            x = sign * (length / 2 - k * chord * 1.25 - chord * 0.6)
            block = G.box_body((chord * 0.3, width * 1.2, width * 1.2), "aluminium",
                               "array_gimbal", (x, 0, z_truss))
            parts += block.parts
            beta = rng.uniform(-30, 30)
            for side in (Y, -Y):
                site = block.toward(side)
                sun = rotation_about(X, alpha) @ G.turned(Z, X, beta)
                local = G.wing(rng, style, span, chord, int(rng.integers(2, 5)), thin,
                               yoke=width * 0.5, embed=site.embed())
                parts += G.wing_at(site, side, sun, local)
    for _ in range(int(pick(rng, (0, 1, 2, 2)))):  # radiator wings hanging off the truss
        x = rng.uniform(0.1, 0.3) * length * pick(rng, (1, -1))
        block = G.box_body((width, width * 1.1, width * 1.1), "aluminium", "radiator_mount",
                           (x, 0, z_truss))
        parts += block.parts
        site = block.toward(pick(rng, (Z, -Y, Y)))
        local = _recolour(G.wing(rng, "rect", rng.uniform(0.1, 0.25) * length,
                                 rng.uniform(2.5, 4.0), int(rng.integers(3, 8)), thin, 1.0,
                                 embed=site.embed()), "radiator", "white_paint")
        parts += G.wing_at(site, site.normal, X, local)
    parts += _module_cluster(rng, thin, mod_r, (0, 0, 0), X if chance(rng, 0.5) else Y,
                             int(rng.integers(2, 7)), branch=0.5)
    return parts


def _module_cluster(rng: np.random.Generator, thin: float, radius: float, centre, axis,
                    count: int, branch: float) -> list[Part]:
    """A node at ``centre`` with chains of modules along +-``axis`` (``count`` in all),
    branching off nodes with probability ``branch``, docked capsules at some ends."""
    node = G.module_body(radius * 1.05, radius * 2.6, "white_paint", centre, axis)
    parts = list(node.parts)
    axis = G.unit(axis)
    lateral = G.perpendicular(axis) if abs(axis @ Z) > 0.5 else G.unit(np.cross(axis, Z))
    ends = [(node, axis), (node, -axis)]
    for k in range(count):
        host, direction = ends[k % len(ends)]
        length = rng.uniform(2.5, 5.0) * radius
        r = radius * rng.uniform(0.8, 1.05)
        start = host.center + direction * host.half[2]
        centre_k = start + direction * (length / 2 - 0.02 * length)
        module = G.module_body(r, length, pick(rng, ("white_paint", "white_paint",
                                                     "silver_mli")), centre_k, direction)
        parts += module.parts
        if chance(rng, 0.35):  # a pair of small wings on the module
            sun = G.turned(Z if abs(direction @ Z) < 0.9 else X, direction, rng.uniform(-30,
                                                                                         30))
            side = G.unit(np.cross(direction, sun))
            for s in (side, -side):
                site = module.toward(s)
                local = G.wing(rng, "rect", length * rng.uniform(0.8, 2.0), length * 0.3,
                               int(rng.integers(2, 5)), thin, 0.4,
                               embed=site.embed(cap=0.5))
                parts += G.wing_at(site, s, sun, local)
        ends[k % len(ends)] = (module, direction)
        if chance(rng, branch):  # a node with a radial module
            turn = pick(rng, (lateral, -lateral, np.cross(direction, lateral)))
            side_site = module.toward(turn)
            arm_len = rng.uniform(2.0, 4.0) * radius
            side_mod = G.module_body(r * 0.9, arm_len, "white_paint",
                                     side_site.point + turn * (arm_len / 2 - 0.3 * r), turn)
            parts += side_mod.parts
    for host, direction in ends:  # docked vehicles at the ends of the chains
        if chance(rng, 0.5):
            tip = host.center + direction * (host.half[2] + 0.02 * radius)
            cap = P.capsule(radius * 0.8, radius * 1.1, thin)
            parts += place(cap, G.orient(-Z, direction), tip + direction * radius * 1.1)
    return parts


def leo_constellation(rng: np.random.Generator, thin: float) -> list[Part]:
    """Constellation satellites (Starlink, OneWeb, Iridium NEXT, Globalstar, Orbcomm):
    flat-panel buses with one or two long arrays hinged at a short end and standing off at an
    angle, phased-array panels on the nadir face and laser terminals; triangular-prism buses
    with phased-array panels canted off their faces and wings at one end; compact boxes with
    a wing pair on yokes. Varies: style, bus aspect, number, span (2-5 x the bus) and angle
    of the arrays, antenna count."""
    style = pick(rng, ("flat", "flat", "prism", "box"))
    if style == "flat":  # Starlink-like: a thin slab
        size = np.array([rng.uniform(2.5, 4.0), rng.uniform(1.1, 2.0), rng.uniform(0.2, 0.5)])
        bus = G.box_body(size, pick(rng, ("silver_mli", "aluminium", "white_paint")))
        parts = list(bus.parts)
        n_wings = int(pick(rng, (1, 1, 2)))
        for end in (X, -X)[:n_wings]:
            site = bus.toward(end, (0, rng.uniform(-0.3, 0.3) * size[1], 0))
            out = G.turned(end, pick(rng, (Z, -Z)), rng.uniform(0, 60))
            local = G.wing(rng, pick(rng, ("rect", "rect", "rollout")),
                           size[0] * rng.uniform(2.0, 4.5), size[1] * rng.uniform(0.8, 1.4),
                           int(rng.integers(4, 11)), thin, rng.uniform(0.1, 0.6),
                           embed=site.embed(cap=0.2))
            parts += G.wing_at(site, out, G.turned(Z, end, rng.uniform(-30, 30)), local)
        for _ in range(int(rng.integers(2, 5))):  # phased arrays on the nadir face
            u, v = rng.uniform(-0.7, 0.7), rng.uniform(-0.6, 0.6)
            w = rng.uniform(0.4, 0.8) * size[1]
            parts += G.box_on(bus.face("-z", u, v), (w, w * rng.uniform(0.6, 1.0), 0.08),
                              "antenna_white", "phased_array")
        for _ in range(int(rng.integers(0, 4))):  # laser terminals on the zenith face
            u, v = rng.uniform(-0.8, 0.8, size=2)
            parts += G.cylinder_on(bus.face("+z", u, v), 0.12, rng.uniform(0.15, 0.35),
                                   "aluminium", "laser_terminal", direction=G.tilted(rng, Z, 30))
        return parts
    if style == "prism":  # Iridium-like: triangular prism, canted panels, wings at the top
        r, length = rng.uniform(0.6, 1.0), rng.uniform(2.5, 4.5)
        bus = G.prism_body(3, r, length, pick(rng, MLI))
        parts = list(bus.parts)
        cant = rng.uniform(5, 40)
        for k in range(3):
            site = bus.side(60 + 120 * k, -0.6)
            panel_len = length * rng.uniform(0.5, 0.8)
            along = G.turned(Z, site.normal, cant)
            panel = place(P.flat_panel("phased_array", "antenna_white", panel_len,
                                       1.3 * r, 2 * thin), None, (panel_len / 2 - 0.1, 0, 0))
            parts += G.mount(panel, site, X, along, Z, site.normal)
            parts += [Part("hinge", "aluminium", P.rod(site.point - site.normal * 0.1,
                                                      site.point + along * 0.2, 0.05))]
        span = length * rng.uniform(0.8, 2.0)
        for azimuth in (0.0, 180.0) if chance(rng, 0.7) else (0.0,):
            site = bus.side(azimuth, 0.9)
            out = G.turned(site.normal, Z, rng.uniform(0, 45))
            local = G.wing(rng, "rect", span, rng.uniform(0.8, 1.4), int(rng.integers(1, 4)),
                           thin, 0.3, embed=site.embed(cap=0.2))
            parts += G.wing_at(site, out, G.turned(Z, out, rng.uniform(-60, 60)), local)
        for _ in range(int(rng.integers(1, 4))):
            u, v = rng.uniform(-0.5, 0.5, size=2)
            parts += G.dish_at(rng, bus.face("-z", u, v), rng.uniform(0.3, 0.6), thin,
                               G.tilted(rng, -Z, 40), mast=rng.uniform(0.05, 0.4))
        return parts
    size = rng.uniform(0.8, 2.0, size=3)  # OneWeb, Globalstar, Orbcomm: compact box
    bus = G.box_body(size, pick(rng, BUS_MATERIALS))
    parts = list(bus.parts)
    yoke = rng.uniform(0.3, 1.5)
    for side in (Y, -Y) if chance(rng, 0.75) else (Y,):
        site = bus.toward(side, (0, 0, rng.uniform(-0.3, 0.3) * size[2]))
        out = G.turned(side, pick(rng, (Z, X)), rng.uniform(0, 30))
        local = G.wing(rng, "rect", float(max(size)) * rng.uniform(1.5, 4.0),
                       float(size[0]) * rng.uniform(0.7, 1.2), int(rng.integers(1, 4)), thin,
                       yoke, embed=site.embed(cap=0.3))
        parts += G.wing_at(site, out, G.turned(Z, out, rng.uniform(-45, 45)), local)
    for _ in range(int(rng.integers(1, 6))):
        u, v = rng.uniform(-0.7, 0.7, size=2)
        parts += G.mount(P.horn_antenna(rng.uniform(0.2, 0.5), rng.uniform(0.15, 0.35),
                                        pyramidal=chance(rng, 0.5)),
                         bus.face("-z", u, v), Z, G.tilted(rng, -Z, 30))
    if chance(rng, 0.4):
        parts += G.box_on(bus.face("+z"), (0.8 * size[0], 0.8 * size[1], 0.1), "antenna_white",
                          "phased_array")
    return parts


def planetary_orbiter(rng: np.random.Generator, thin: float) -> list[Part]:
    """Planetary orbiters (Mars Reconnaissance Orbiter, MAVEN, Mars Express, Mars Odyssey, TGO,
    LRO, Venus Express): a box bus over a main engine, a large high-gain dish fixed on top,
    on the side, or on a deployment boom; twin wings (flat, crosses or MAVEN-like gull wings)
    or a single wing on a yoke; an articulated payload platform on an arm, long radar dipoles
    crossing the bus, magnetometer masts. Varies: dish size and mount (fixed or boom), power
    layout and angles, the payload arm, dipole length (6-16 x the bus tip to tip, 3-8 each
    side)."""
    size = np.array([rng.uniform(1.4, 3.0), rng.uniform(1.4, 2.6), rng.uniform(1.2, 3.0)])
    bus = G.box_body(size, pick(rng, MLI))
    parts = list(bus.parts)
    body = float(max(size))
    power = pick(rng, ("twin", "twin", "gull", "single"))
    sun = G.turned(Z, X, rng.uniform(-40, 40))
    if power == "single":
        site = bus.toward(pick(rng, (Y, -Y)), (rng.uniform(-0.3, 0.3) * size[0], 0,
                                               rng.uniform(-0.3, 0.3) * size[2]))
        out = G.tilted(rng, site.normal, 40, 10)
        local = G.wing(rng, pick(rng, ("rect", "double")), body * rng.uniform(1.5, 3.5),
                       body * rng.uniform(0.6, 1.2), int(rng.integers(2, 5)), thin,
                       rng.uniform(0.5, 2.0), embed=site.embed(cap=0.4))
        parts += G.wing_at(site, out, sun, local)
    else:
        style = "gull" if power == "gull" else pick(rng, ("rect", "rect", "cross"))
        parts += G.wing_pair_at(bus, rng, style, body * rng.uniform(1.2, 3.0),
                                body * rng.uniform(0.5, 1.0), int(rng.integers(2, 6)), thin, Y,
                                sun, yoke=rng.uniform(0.3, 1.2), cant_deg=rng.uniform(-20, 20),
                                height=rng.uniform(-0.5, 0.5))
    dish_d = body * rng.uniform(0.8, 1.6)
    mount = pick(rng, ("top", "boom", "boom", "side"))
    if mount == "top":  # fixed on the top deck (MAVEN)
        parts += G.dish_at(rng, bus.face("+z"), dish_d, thin, G.tilted(rng, Z, 15),
                           mast=rng.uniform(0.05, 0.4))
    elif mount == "side":  # fixed on a side (Mars Express, Odyssey-like)
        site = bus.toward(X, (0, 0, rng.uniform(-0.3, 0.3) * size[2]))
        parts += G.dish_at(rng, site, dish_d * 0.8, thin, G.tilted(rng, X, 20), mast=0.1)
    else:  # on a deployment boom, gimballed (MRO, LRO)
        site = bus.toward(pick(rng, (X, -X, Z)))
        arm = G.tilted(rng, site.normal, 60, 20)
        r = G.rod_radius(0.07, thin)
        boom, tip = G.boom_from(site, arm, rng.uniform(1.0, 3.0), r, "antenna_boom")
        block = G.tip_block(tip, 3.5 * r)
        facing = G.tilted(rng, Z, 70)
        parts += boom + block.parts + G.dish_at(rng, block.toward(facing), dish_d, thin,
                                                facing, mast=0.15)
    if chance(rng, 0.5):  # articulated payload platform on an arm
        site = bus.toward(-Z, (rng.uniform(-0.3, 0.3) * size[0], 0, 0))
        boom, tip = G.boom_from(site, G.tilted(rng, -Z, 60, 20), rng.uniform(1.0, 2.5),
                                G.rod_radius(0.06, thin), "payload_arm")
        block = G.tip_block(tip, 0.6, "gold_mli", "payload_platform", up=Z)
        parts += boom + block.parts + _instruments(rng, block, -Z, 2, 0.4)
    else:
        parts += _instruments(rng, bus, -Z, int(rng.integers(2, 5)), 0.45 * body)
    if chance(rng, 0.4):  # radar dipole crossing the bus (MARSIS, SHARAD)
        site = bus.toward(-Z)
        block = G.box_body((0.4, 0.4, 0.3), "aluminium", "antenna_mount",
                           site.point - 0.05 * Z)
        parts += block.parts
        half = body * rng.uniform(3.0, 8.0)
        direction = G.turned(X, Y, rng.uniform(-60, 60))
        parts += [Part("dipole_antenna", "aluminium",
                       P.rod(block.center - half * direction, block.center + half * direction,
                             G.rod_radius(0.02, thin), 6))]
    if chance(rng, 0.3):
        site = bus.toward(pick(rng, (X, -X)))
        parts += _magnetometer(site, G.tilted(rng, site.normal, 45), body *
                               rng.uniform(1.0, 2.5), thin)
    parts += place(P.thruster_nozzle(0.7, 0.3), None, bus.face("-z", 0.3, 0.3).point)
    parts += _star_trackers(rng, bus, Z, 2, 0.25)
    return parts


def heliophysics(rng: np.random.Generator, thin: float) -> list[Part]:
    """Solar and heliospheric observatories (SOHO, SDO, Solar Orbiter, STEREO, ACE, Parker):
    a sun-pointed bus, sometimes behind a heat shield; twin wings fixed in a V towards the
    sun or canted; an instrument module with telescopes looking sunwards; one or two
    high-gain dishes on masts; an instrument boom and wire antennas. Varies: heat shield or
    instrument module, wing angles and span, dish count and masts, boom length (1-4 x the
    bus)."""
    size = np.array([rng.uniform(1.2, 2.6), rng.uniform(1.2, 2.5), rng.uniform(1.2, 3.0)])
    bus = G.box_body(size, pick(rng, BUS_MATERIALS))
    parts = list(bus.parts)
    body = float(max(size))
    sunward = X
    if chance(rng, 0.45):  # a heat shield on struts in front (Solar Orbiter, Parker)
        gap = rng.uniform(0.2, 0.8)
        front = bus.toward(X)
        shield_w = body * rng.uniform(1.1, 1.8)
        if chance(rng, 0.5):
            shield = P.heat_shield(shield_w / 2, rng.uniform(0.1, 0.25))
        else:
            shield = P.flat_panel("heat_shield", "dark_composite", shield_w, shield_w * 0.9,
                                  0.2)
        parts += G.mount(shield, front, Z, X, lift=gap)
        for k in range(4):
            a = np.radians(45 + 90 * k)
            root = front.point + 0.3 * np.array([0, size[1] * np.cos(a), size[2] * np.sin(a)])
            parts.append(Part("truss", "dark_composite",
                              P.rod(root - 0.1 * X, root + (gap + 0.05) * X + 0.2 * (
                                  root - front.point), G.rod_radius(0.04, thin), 6)))
    else:  # an instrument module with sun-looking telescopes (SOHO, SDO)
        depth = rng.uniform(0.6, 1.5)
        module = G.box_body((depth, size[1] * 0.8, size[2] * 0.8),
                            pick(rng, ("white_paint", "silver_mli")), "instrument_module",
                            bus.toward(X).point + X * (depth / 2 - 0.1))
        parts += module.parts
        for _ in range(int(rng.integers(1, 5))):
            u, v = rng.uniform(-0.6, 0.6, size=2)
            site = module.face("+x", u, v)
            parts += G.mount(P.telescope_tube(rng.uniform(0.1, 0.3), rng.uniform(0.4, 1.4),
                                              0.02, door=False), site, Z,
                             G.tilted(rng, X, 5), lift=-0.05)
    vee = rng.uniform(0, 35)  # wings swept back, away from the sun (as Parker's)
    span = body * rng.uniform(1.0, 3.0)
    for side in (Y, -Y):
        site = bus.toward(side, (rng.uniform(-0.3, 0.0) * size[0], 0, 0))
        out = G.turned(side, -sunward, vee)
        local = G.wing(rng, pick(rng, ("rect", "rect", "cross")), span,
                       body * rng.uniform(0.5, 1.0), int(rng.integers(1, 4)), thin,
                       rng.uniform(0.2, 0.8), embed=site.embed(cap=0.3))
        parts += G.wing_at(site, out, sunward, local)
    for _ in range(int(pick(rng, (1, 1, 2)))):  # high-gain dishes on masts (SDO, STEREO)
        site = bus.toward(pick(rng, (Z, -Z, -X)), (rng.uniform(-0.3, 0.3) * size[0], 0, 0))
        boom, tip = G.boom_from(site, G.tilted(rng, site.normal, 50, 10),
                                body * rng.uniform(0.3, 1.2), G.rod_radius(0.05, thin),
                                "antenna_boom")
        block = G.tip_block(tip, 0.2)
        facing = G.tilted(rng, -sunward, 80)
        parts += boom + block.parts + G.dish_at(rng, block.toward(facing),
                                                body * rng.uniform(0.4, 1.0), thin, facing,
                                                mast=0.05)
    if chance(rng, 0.6):  # instrument boom in the shade
        site = bus.toward(-X)
        parts += _magnetometer(site, G.tilted(rng, -X, 45), body * rng.uniform(1.0, 4.0), thin)
    for _ in range(int(rng.integers(0, 3))):
        site = bus.toward(G.turned(-X, pick(rng, (Y, -Y, Z, -Z)), 60))
        boom, _tip = G.boom_from(site, G.tilted(rng, site.normal, 40),
                                 body * rng.uniform(1.5, 3.5), G.rod_radius(0.015, thin),
                                 "wire_antenna")
        parts += boom
    parts += _star_trackers(rng, bus, Z, 2, 0.25)
    return parts


def observatory(rng: np.random.Generator, thin: float) -> list[Part]:
    """Space telescopes in tubes (Hubble, Chandra, Kepler, Spitzer, Swift, XMM-Newton, Roman,
    Euclid, CoRoT): one tube (or three in parallel) on a service module; power from wings at
    mid-tube or at the base, or from a one-sided fixed array standing along the tube; dishes
    on masts, aperture doors, radiators. Varies: tube radius and length (2.5-9 x radius),
    tube count, service module shape and length, power layout and span, dish count."""
    radius = rng.uniform(0.6, 2.0)
    length = radius * rng.uniform(2.5, 9.0)
    triple = chance(rng, 0.15)
    base_h = length * rng.uniform(0.12, 0.35)
    shape = pick(rng, ("oct", "cyl", "hex", "box"))
    base_r = radius * (2.4 if triple else rng.uniform(1.0, 1.3))
    base = _bus(shape, np.array([2 * base_r, 2 * base_r, base_h]), pick(rng, MLI))
    parts = list(base.parts)
    top = base.face("+z")
    tube_r = radius * (0.75 if triple else 1.0)
    door = chance(rng, 0.4)
    centres = [np.zeros(3)]
    if triple:
        centres = [1.25 * tube_r * np.array([np.cos(a), np.sin(a), 0])
                   for a in np.radians([90, 210, 330])]
    for c in centres:
        parts += place(P.telescope_tube(tube_r, length, thin, door=door), None,
                       top.point + c - 0.1 * Z)
    power = pick(rng, ("mid", "mid", "base", "one_sided", "vee"))
    span = length * rng.uniform(0.4, 1.0)
    chord = min(span * rng.uniform(0.25, 0.5), 1.2 * length)
    if power in ("mid", "base"):  # wings from the tube (Hubble) or the base (Chandra)
        z = top.point[2] + length * rng.uniform(0.2, 0.6) if power == "mid" else 0.0
        host = G.prism_body(32, tube_r, 2 * length, "silver_mli") if power == "mid" else base
        cant = rng.uniform(-60, 60)
        for side in (X, -X):
            site = host.toward(side, (0, 0, z))
            local = G.wing(rng, pick(rng, ("rect", "double")), span, chord,
                           int(rng.integers(1, 4)), thin, radius * 0.4,
                           embed=site.embed(cap=0.3))
            parts += G.wing_at(site, side, rotation_about(side, cant) @ Y, local)
    elif power == "one_sided":  # a fixed array along one side of the tube (Kepler, Spitzer)
        outer = 1.35 * tube_r if not triple else 2.8 * tube_r
        facets = int(pick(rng, (1, 2, 3)))
        height = length * rng.uniform(0.6, 1.0)
        width = 2 * tube_r * rng.uniform(0.9, 1.4)
        for k in range(facets):
            a = (k - (facets - 1) / 2) * rng.uniform(25, 40)
            normal = rotation_about(Z, a) @ -Y
            centre = top.point + normal * outer + Z * (height / 2 + 0.05 * length)
            panel = P.flat_panel("solar_panel", "solar_cell", width / facets * 1.08, height,
                                 1.5 * thin)
            parts += place(panel, G.orient(Z, normal, Y, Z), centre)
            axis = max(centres, key=lambda c: float(c @ normal))  # the tube nearest the panel
            for zf in (0.25, 0.75):  # struts from that tube's axis to the panel
                p1 = centre + Z * (zf - 0.5) * height
                p0 = np.array([axis[0], axis[1], p1[2]])
                parts.append(Part("array_strut", "aluminium",
                                  P.rod(p0, p1, G.rod_radius(0.05, thin), 6)))
    else:  # two fixed panels in a V on the base (Swift, Fermi)
        for side in (X, -X):
            site = base.toward(side)
            out = G.turned(side, -Z, rng.uniform(0, 35))
            local = G.wing(rng, "rect", span * 0.6, chord, 1, thin, 0.2,
                           embed=site.embed(cap=0.3))
            parts += G.wing_at(site, out, G.turned(Y, Z, rng.uniform(-30, 30)), local)
    for _ in range(int(pick(rng, (0, 1, 2, 2)))):  # dishes on masts
        z = top.point[2] + length * rng.uniform(0.05, 0.4)
        azimuth = rng.uniform(0, 360)
        host = G.prism_body(32, tube_r, 2 * length, "silver_mli") if not triple else base
        site = host.side(azimuth, 0.0) if triple else host.toward(
            rotation_about(Z, azimuth) @ X, (0, 0, z))
        boom, tip = G.boom_from(site, G.tilted(rng, site.normal, 30),
                                radius * rng.uniform(0.8, 2.0), G.rod_radius(0.06, thin),
                                "antenna_mast")
        block = G.tip_block(tip, 0.25)
        facing = G.tilted(rng, site.normal, 90)
        parts += boom + block.parts + G.dish_at(rng, block.toward(facing),
                                                radius * rng.uniform(0.5, 0.9), thin, facing,
                                                mast=0.05)
    parts += _radiators(rng, base, thin, int(rng.integers(0, 4)), 0.8 * base_r)
    parts += G.mount(P.star_tracker(0.35), base.face("-z", 0.4, 0.4), Z,
                     G.tilted(rng, -Z, 40))
    return parts


def infrared_observatory(rng: np.random.Generator, thin: float) -> list[Part]:
    """Cold observatories behind sunshields (JWST, Herschel, Planck, Gaia): a layered kite
    sunshield under a tower with a segmented mirror, its secondary on a tripod and an
    instrument module behind (JWST); or a service module with a wide round multi-layer skirt
    and a telescope on top (Planck, Gaia); or a tall cryostat with a dish on top and a flat
    sunshade of cells on one side (Herschel). Varies: style, shield size (2-8 x the bus) and
    layers, mirror segments and tilt, tower height, skirt size, panel and dish placement."""
    style = pick(rng, ("layered", "layered", "skirt", "cryostat"))
    if style == "layered":
        bus = G.box_body(rng.uniform(1.2, 2.5, size=3), pick(rng, MLI))
        length = float(max(bus.size)) * rng.uniform(4.0, 9.0)
        layers, gap = int(rng.integers(3, 6)), rng.uniform(0.15, 0.4)
        shield = P.layered_shield(length, length * rng.uniform(0.5, 0.75), layers, gap, thin)
        depth = (layers - 1) * gap + 2 * thin
        offset = np.array([rng.uniform(-0.4, 0.4) * bus.half[0], 0, depth + bus.half[2] - 0.3])
        parts = place(shield, None, offset) + list(bus.parts)  # bus under the stack's centre
        top = offset + thin * Z
        tower = rng.uniform(0.5, 2.5)
        aim = G.turned(Z, X, rng.uniform(20, 80))  # the mirror looks off the shield's normal
        seg = rng.uniform(0.5, 1.1)
        rings = int(pick(rng, (1, 2, 2)))
        boom, tip = G.boom_from(G.Site(top, Z, 0.2), Z, tower, G.rod_radius(0.15, thin),
                                "tower")
        block = G.tip_block(tip, 1.0, "dark_composite", "instrument_module", up=X,
                            shape=(1.2, 1.2, 1.0))
        parts += boom + block.parts
        focal = seg * (rings + 1) * rng.uniform(2.5, 4.0)
        mirror = P.segmented_mirror(seg, rings, focal, thin)
        reach = seg * np.sqrt(3) * rings
        for a in np.radians([90, 210, 330]):  # secondary on a tripod
            foot = (reach * 0.9 * np.cos(a), reach * 0.9 * np.sin(a), 0.0)
            mirror.append(Part("tripod", "aluminium",
                               P.rod(foot, (0, 0, focal * 0.9), G.rod_radius(0.04, thin), 6)))
        mirror.append(Part("secondary_mirror", "gold_mli",
                           P.transform_solid(P.prism(6, seg * 0.5, 0.15), None,
                                             (0, 0, focal * 0.9))))
        face = block.toward(aim)
        parts += G.mount(mirror, face, Z, aim, lift=0.05)
        site = bus.toward(-Z)
        local = G.wing(rng, "rect", length * rng.uniform(0.2, 0.4), float(max(bus.size)), 1,
                       thin, 0.3, embed=site.embed(cap=0.3))
        parts += G.wing_at(bus.toward(-X), G.turned(-X, -Z, rng.uniform(0, 40)), -Z, local)
        parts += G.dish_at(rng, site, rng.uniform(0.4, 1.0), thin, G.tilted(rng, -Z, 40),
                           mast=0.3)
        return place(parts, rotation_about(X, 180))  # the mirror's side up in previews
    if style == "skirt":
        r, h = rng.uniform(1.2, 2.2), rng.uniform(1.0, 2.2)
        bus = G.prism_body(int(pick(rng, (6, 8, 32))), r, h, pick(rng, MLI))
        parts = list(bus.parts)
        skirt_r = r * rng.uniform(1.8, 4.0)
        sides = int(pick(rng, (6, 12, 32)))
        for k in range(int(rng.integers(1, 4))):  # stacked skirt layers on a hub
            z = -h / 2 - k * 0.25
            parts.append(Part("sunshield", pick(rng, ("solar_cell", "silver_mli")),
                              P.transform_solid(P.prism(sides, skirt_r * (1 - 0.12 * k),
                                                        2 * thin), None, (0, 0, z))))
        parts.append(Part("skirt_hub", "aluminium", P.transform_solid(
            P.prism(16, r * 0.5, 0.3 * 3 + 0.2), None, (0, 0, -h / 2 - 0.3))))
        top = bus.face("+z")
        if chance(rng, 0.5):  # Planck: an offset dish in a baffle of walls
            w = 2 * r * 0.9
            dish_d = w * 0.8
            facing = G.turned(Z, X, rng.uniform(20, 70))
            parts += G.dish_at(rng, top.offset((-0.2 * r, 0, 0)), dish_d, thin, facing,
                               mast=0.3)
            wall_h = dish_d * rng.uniform(0.6, 1.1)
            for k in range(3):
                a = np.radians(90 * k + 90)
                c = top.point + np.array([np.cos(a), np.sin(a), 0]) * w / 2 + Z * (
                    wall_h / 2 - 0.05)
                wall = P.box((thin * 2, w, wall_h)) if k % 2 == 1 else P.box((w, thin * 2,
                                                                             wall_h))
                parts.append(Part("baffle", "silver_mli", P.transform_solid(wall, None, c)))
        else:  # Gaia-like: a payload box with two telescopes
            pay_h = h * rng.uniform(0.6, 1.2)
            pay = G.box_body((r * 1.3, r * 1.3, pay_h), "dark_composite", "payload_module",
                             top.point + Z * (pay_h / 2 - 0.1))
            parts += pay.parts
            for a in (rng.uniform(0, 180), rng.uniform(180, 360)):
                site = pay.side(a)
                parts += G.mount(P.telescope_tube(r * 0.25, r * 0.5, thin, door=False), site,
                                 Z, site.normal, lift=-0.1)
        parts += G.dish_at(rng, bus.face("-z", 0.3, 0.0), rng.uniform(0.3, 0.8), thin,
                           G.tilted(rng, -Z, 50), mast=0.3)
        return parts
    # cryostat (Herschel): a tall tank on a service module, a dish on top, a flat shade
    r = rng.uniform(0.9, 1.4)
    svc = G.prism_body(int(pick(rng, (6, 8))), r * 1.3, rng.uniform(0.8, 1.5), pick(rng, MLI))
    tank_h = rng.uniform(2.5, 5.0)
    tank = G.prism_body(32, r, tank_h, "silver_mli", "cryostat",
                        svc.face("+z").point + Z * (tank_h / 2 - 0.1))
    parts = list(svc.parts) + list(tank.parts)
    dish_d = r * rng.uniform(2.2, 3.2)
    parts += G.dish_at(rng, tank.face("+z"), dish_d, thin, G.tilted(rng, Z, 15),
                       mast=rng.uniform(0.3, 0.8))
    height = tank_h + svc.size[2]
    shade_w = 2 * r * rng.uniform(1.1, 1.6)
    side = rotation_about(Z, rng.uniform(0, 360)) @ X
    centre = svc.center + side * (r * 1.4) + Z * (height / 2 - svc.half[2])
    parts += place(P.flat_panel("sunshield", "solar_cell", shade_w, height * 1.05, 2 * thin),
                   G.orient(Z, side, Y, Z), centre)
    for zf in (0.2, 0.85):
        p1 = svc.center + side * (r * 1.4) + Z * (zf * height - svc.half[2])
        parts.append(Part("sunshield_strut", "aluminium",
                          P.rod(p1 - side * r * 0.9, p1, G.rod_radius(0.05, thin), 6)))
    return parts


def boom_science(rng: np.random.Generator, thin: float) -> list[Part]:
    """Space-physics spacecraft whose booms set their size (THEMIS, MMS, Cluster, Van Allen
    Probes, Polar, Swarm, CHAMP): a spinning drum with radial wire booms 5-25 x its radius,
    axial booms and magnetometer masts; an octagonal drum with radial panels carrying
    magnetometer booms at their tips; or a long slender bus with a boom at its front.
    Varies: style, boom count (2-6), lengths, elevations and spacing, panel count."""
    style = pick(rng, ("spinner", "spinner", "panels", "slender"))
    if style == "slender":  # Swarm, CHAMP, GOCE-like
        size = np.array([rng.uniform(3.0, 7.0), rng.uniform(0.7, 1.6), rng.uniform(0.5, 1.0)])
        shape = pick(rng, ("box", "oct"))
        bus = _bus(shape, np.array([size[1], size[1], size[0]]), pick(rng, MLI), axis=X)
        parts = list(bus.parts)
        parts += G.box_on(bus.toward(Z), (size[0] * 0.8, size[1] * 0.8, thin * 2), "solar_cell",
                          "body_cells", up=X)
        boom_len = size[0] * rng.uniform(0.6, 1.5)
        parts += _magnetometer(bus.toward(X), G.tilted(rng, X, 10), boom_len, thin)
        if chance(rng, 0.5):  # fixed fins of cells (GOCE)
            for side in (Y, -Y):
                site = bus.toward(side)
                local = G.wing(rng, "rect", size[1] * rng.uniform(0.6, 1.5), size[0] * 0.6, 1,
                               thin, 0.05, embed=site.embed(cap=0.2))
                parts += G.wing_at(site, side, Z, local)
        else:  # a canted panel pair on the roof (Swarm)
            for side in (Y, -Y):
                site = bus.toward(G.turned(Z, side, 50))
                local = G.wing(rng, "rect", size[1] * 0.8, size[0] * 0.7, 1, thin, 0.05,
                               embed=site.embed(cap=0.2))
                parts += G.wing_at(site, G.turned(side, Z, rng.uniform(20, 50)), Z, local)
        return parts
    r = rng.uniform(0.4, 1.2)
    h = r * rng.uniform(0.4, 1.3)
    sides = int(pick(rng, (8, 8, 16, 32)))
    bus = G.prism_body(sides, r, h, pick(rng, ("aluminium", "solar_cell", "gold_mli")))
    parts = list(bus.parts)
    if sides <= 16:  # body-mounted cells on the facets
        apothem = bus.half[1]
        width = 2 * r * np.sin(np.pi / sides) * 0.9
        for k in range(sides):
            plate = P.box((thin, width, h * 0.85), (apothem + thin / 4, 0, 0))
            a = bus._face_normals()[k]
            parts.append(Part("body_cells", "solar_cell",
                              P.transform_solid(plate, rotation_about(Z, np.degrees(
                                  np.arctan2(a[1], a[0]))))))
    phase = rng.uniform(0, 360)
    if style == "panels":  # Van Allen Probes: radial panels with booms at their tips
        n_pan = 4
        span = r * rng.uniform(1.5, 3.0)
        for k in range(n_pan):
            site = bus.side(phase + 90 * k, 0.6)
            local = G.wing(rng, "rect", span, r * 0.9, 1, thin, 0.2, embed=site.embed(cap=0.3))
            parts += G.wing_at(site, site.normal, Z, local)
            if k % 2 == 0:  # magnetometer boom from the panel's tip
                tip = G.Site(site.point + site.normal * (0.2 + span * 0.97), site.normal,
                             thin)
                parts += _magnetometer(tip, G.turned(site.normal, Z, rng.uniform(-10, 10)),
                                       r * rng.uniform(2.5, 5.0), thin)
        phase += 45
    n_wire = int(pick(rng, (2, 4, 4, 6)))
    wire_len = r * rng.uniform(5.0, 25.0)
    for k in range(n_wire):
        site = bus.side(phase + 360 * k / n_wire + rng.uniform(-8, 8), rng.uniform(-0.3, 0.3))
        out = G.turned(site.normal, Z, rng.uniform(-8, 8))
        boom, tip = G.boom_from(site, out, wire_len * rng.uniform(0.85, 1.0),
                                G.rod_radius(0.01, thin), "wire_boom")
        parts += boom + G.tip_block(tip, 2.5 * G.rod_radius(0.01, thin), "aluminium",
                                    "probe_sphere").parts
    for sign in (1.0, -1.0)[: int(pick(rng, (0, 1, 2, 2)))]:  # axial booms
        site = bus.face("+z" if sign > 0 else "-z")
        boom, _tip = G.boom_from(site, G.tilted(rng, sign * Z, 5),
                                 r * rng.uniform(2.0, 6.0), G.rod_radius(0.03, thin),
                                 "axial_boom")
        parts += boom
    if style == "spinner":
        for k in range(int(pick(rng, (1, 2, 2)))):
            site = bus.side(phase + 180 / n_wire + 180 * k, 0.0)
            parts += _magnetometer(site, G.turned(site.normal, Z, rng.uniform(-20, 20)),
                                   r * rng.uniform(2.0, 6.0), thin)
    for _ in range(int(rng.integers(0, 3))):
        u, v = rng.uniform(-0.5, 0.5, size=2)
        parts += G.box_on(bus.face("+z", u, v), rng.uniform(0.15, 0.4, size=3) * r * 2,
                          pick(rng, ("white_paint", "gold_mli")), "instrument", aperture=True)
    return parts


def crewed_cargo(rng: np.random.Generator, thin: float) -> list[Part]:
    """Crew and cargo vehicles (Soyuz, Progress, Shenzhou, Orion, Dragon, Cygnus, ATV, HTV,
    Tianzhou, Apollo CSM): a capsule or a pressurised cargo module on a service module, an
    orbital module in front, and arrays: one pair, four canted in an X, two round UltraFlex
    discs, or none (an engine bell, a dish on a boom). Varies: modules, their proportions,
    array layout, count, span and cant."""
    rs = rng.uniform(1.0, 2.2)
    svc_len = rs * rng.uniform(1.0, 3.0)
    svc = G.prism_body(32, rs, svc_len, pick(rng, ("white_paint", "silver_mli", "gold_mli",
                                                    "aluminium")), "service_module")
    parts = list(svc.parts)
    front = pick(rng, ("capsule", "capsule", "cargo"))
    top = svc.face("+z")
    if front == "capsule":
        cap_h = rs * rng.uniform(0.7, 1.3)
        parts += place(P.capsule(rs * rng.uniform(0.9, 1.05), cap_h, thin), None,
                       top.point - 0.05 * Z)
        if chance(rng, 0.4):  # Soyuz orbital module
            orb_r = rs * 0.6
            parts += place(P.pressurised_module(orb_r, orb_r * 2.4, "white_paint", 0.35), None,
                           top.point + Z * (cap_h + orb_r * 1.1))
    else:
        cargo_len = rs * rng.uniform(1.5, 4.0)
        parts += place(P.pressurised_module(rs * 0.98, cargo_len, "white_paint", 0.15), None,
                       top.point + Z * (cargo_len / 2 - 0.1))
    arrays = pick(rng, ("pair", "x4", "discs", "none"))
    span = rs * rng.uniform(2.0, 6.0)
    sun = G.turned(Z, X, rng.uniform(-60, 60))
    if arrays == "pair":
        parts += G.wing_pair_at(svc, rng, pick(rng, ("rect", "rect", "rollout")), span,
                                rs * rng.uniform(0.6, 1.0), int(rng.integers(2, 6)), thin, Y,
                                sun, yoke=0.3, cant_deg=rng.uniform(-30, 30))
    elif arrays == "x4":  # Orion, ATV: four wings in an X, swept back
        sweep = rng.uniform(0, 30)
        for k in range(4):
            site = svc.side(45 + 90 * k, rng.uniform(-0.6, 0.0))
            out = G.turned(site.normal, -Z, sweep)
            local = G.wing(rng, "rect", span * 0.8, rs * rng.uniform(0.6, 1.0),
                           int(rng.integers(2, 5)), thin, 0.3, embed=site.embed(cap=0.3))
            parts += G.wing_at(site, out, G.turned(Z, out, 90), local)
    elif arrays == "discs":  # Cygnus: two round arrays
        for side in (Y, -Y):
            site = svc.toward(side)
            local = G.wing(rng, "circular", rs * rng.uniform(1.8, 3.5), 0.0, 1, thin, 0.4,
                           embed=site.embed(cap=0.3))
            parts += G.wing_at(site, G.turned(side, -Z, rng.uniform(0, 20)), sun, local)
    else:  # Apollo-like: a big engine bell and a dish on a boom
        site = svc.side(rng.uniform(0, 360), -0.8)
        boom, tip = G.boom_from(site, G.turned(site.normal, -Z, 40), rs * 1.2,
                                G.rod_radius(0.06, thin))
        block = G.tip_block(tip, 0.3)
        parts += boom + block.parts
        for _ in range(int(pick(rng, (1, 4)))):
            facing = G.tilted(rng, -Z, 60)
            parts += G.dish_at(rng, block.toward(facing), rs * 0.4, thin, facing, mast=0.05)
    bell = rs * rng.uniform(0.3, 0.7)
    parts += place(P.thruster_nozzle(bell * 1.6, bell), None, svc.face("-z").point)
    return parts


def module_stack(rng: np.random.Generator, thin: float) -> list[Part]:
    """Modular stations without a long truss (Mir, Salyut, Skylab, Tiangong, Gateway): chains
    of pressurised modules from a core node, radial modules off nodes (crosses and Ts),
    arrays on the modules (pairs, Skylab's windmill of four on a mount, a single large
    wing, round discs on the power module), docked capsules. Varies: module count (3-11, the
    node included),
    lengths, branching, array layouts and angles."""
    radius = rng.uniform(1.8, 2.3)
    parts = _module_cluster(rng, thin, radius, (0, 0, 0), X, int(rng.integers(2, 6)),
                            branch=0.6)
    extra = pick(rng, ("windmill", "big_wing", "discs", "none"))
    node_len = radius * 2.6
    if extra == "windmill":  # Skylab's telescope mount: four wings in an X on a drum
        drum = G.prism_body(8, radius * 0.9, radius * 1.2, "white_paint", "telescope_mount",
                            (0, 0, radius * 1.05 + radius * 0.6 - 0.2))
        parts += drum.parts
        span = radius * rng.uniform(3.0, 6.0)
        phase = rng.uniform(0, 90)
        for k in range(4):
            site = drum.side(phase + 90 * k)
            local = G.wing(rng, "rect", span, radius * rng.uniform(1.0, 1.6), 3, thin, 0.3,
                           embed=site.embed(cap=0.4))
            parts += G.wing_at(site, site.normal, Z, local)
    elif extra == "big_wing":  # one large wing on the core (Skylab's surviving wing)
        site = G.module_body(radius * 1.05, node_len, "white_paint", (0, 0, 0), X).toward(Y)
        local = G.wing(rng, pick(rng, ("rect", "double")), radius * rng.uniform(4, 8),
                       radius * rng.uniform(1.5, 2.5), int(rng.integers(2, 5)), thin, 0.5,
                       embed=site.embed(cap=0.5))
        parts += G.wing_at(site, G.tilted(rng, Y, 25), Z, local)
    elif extra == "discs":  # a power module with round or roll-out arrays (Gateway)
        site = G.module_body(radius * 1.05, node_len, "white_paint", (0, 0, 0), X).toward(Z)
        ppe = G.box_body((radius * 1.6, radius * 1.6, radius * 1.5), "gold_mli",
                         "power_module", site.point + Z * (radius * 0.75 - 0.3))
        parts += ppe.parts
        style = pick(rng, ("circular", "rollout"))
        for side in (Y, -Y):
            s = ppe.toward(side)
            local = G.wing(rng, style, radius * rng.uniform(3.0, 6.0), radius * 1.5, 1, thin,
                           0.5, embed=s.embed(cap=0.4))
            parts += G.wing_at(s, side, G.turned(X, Z, rng.uniform(-45, 45)), local)
    return parts


FAMILIES: dict[str, Recipe] = {
    "boom_science": boom_science,
    "comms_relay": comms_relay,
    "crewed_cargo": crewed_cargo,
    "deep_space_probe": deep_space_probe,
    "earth_observer": earth_observer,
    "heliophysics": heliophysics,
    "infrared_observatory": infrared_observatory,
    "leo_constellation": leo_constellation,
    "module_stack": module_stack,
    "observatory": observatory,
    "planetary_orbiter": planetary_orbiter,
    "sep_probe": sep_probe,
    "smallsat": smallsat,
    "station_truss": station_truss,
}
"""The families of the compositional generator, by name (the catalogue's ``archetype``)."""

HELD_OUT_FAMILIES: frozenset[str] = frozenset({
    "infrared_observatory", "module_stack", "planetary_orbiter"})
"""The fixed leave-family-out set: families never trained on, tuned on or selected on.

They measure how a network generalises to spacecraft *classes* it has not seen, built from
parts and attachments it has seen in other families: a probe (``planetary_orbiter``: dishes
on booms, gull wings, radar dipoles; dishes and booms appear in ``deep_space_probe``,
``heliophysics`` and ``sep_probe``, gull wings in ``smallsat``, dipoles in no training
family), an observatory (``infrared_observatory``: layered sunshields, segmented mirrors,
cryostats; tubes, dishes and shields appear in ``observatory`` and ``heliophysics``; its
Planck/Gaia "skirt" and Herschel "cryostat" styles, about half of its models, are close to
the old archetype ``sunshade_observatory``, which the archetype-trained models saw: only its
JWST-like style is far from everything trained on) and a human-spaceflight cluster
(``module_stack``: module chains, radial crosses, windmill arrays; built by the module
cluster ``station_truss`` uses too, so its chains, crosses, docked capsules and wings on
modules come from a training family's code path: what is new is their scale and count).
Three of the fourteen families (about a fifth), one from each group, none of the simplest.
Their models are in the ``"test"`` split of
:func:`~sq_mitsuba.data.spacecraft.generator.composed_catalogue` (see ``is_held_out``).

Changing this set (or a held-out family's recipe, or a helper it shares with a training
family: tests/test_composer.py pins their geometry) invalidates every comparison made with
it: a network trained with a family in its training set has seen that family.
"""
TRAINING_FAMILIES: frozenset[str] = frozenset(FAMILIES) - HELD_OUT_FAMILIES
"""The families a network may train on: :data:`FAMILIES` less :data:`HELD_OUT_FAMILIES`."""
