"""Free-form part graphs: spacecraft whose structure is drawn, not taken from a template.

The families (:mod:`sq_mitsuba.data.spacecraft.families`) each follow a real class's layout,
so a network trained on them can learn fourteen layouts instead of reading structure. This
recipe draws the structure itself: a core host, then a random tree of attachments, each
fixed to a host already built (the core, a body added before, a platform at a boom's tip),
at any point of it and in any direction. The attachments are the families' parts:

* bodies straight on the host, on a strut, or at the end of a truss (new hosts: chains,
  branches and off-axis clusters of modules and boxes);
* booms and masts, bare, with a sensor, or with a platform at the tip (a new host, so a
  dish or a wing can sit at the end of a boom);
* arrays of every style, 1-8 times the host; dishes on short or long masts; flat panels
  (sunshades, radiators) flat on a face or standing as fins; instruments.

An attachment is, at random, single, paired on the opposite side (a half turn about a host
axis), or repeated 3-4 times about that axis, as real layouts are; the copies are the same
attachment turned (their parameters come from one sub-seed, their second axis turns with
them). Directions are mostly the spacecraft's main axis or a host's axis (slightly tilted),
else any direction out of the host.

Same conventions as the families: ``part_graph(rng, thin)`` returns the parts in the body
frame, draws its random numbers from ``rng`` in a fixed order that does not depend on
``thin``, and builds one connected body (each attachment reaches into its host).

It is not one of :data:`~sq_mitsuba.data.spacecraft.families.FAMILIES`: the compositional
catalogue permutes those, and adding one would change every catalogue made before (the
held-out set among them). It has its own catalogue,
:func:`~sq_mitsuba.data.spacecraft.generator.graph_catalogue`.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from sq_mitsuba.data.spacecraft import grammar as G
from sq_mitsuba.data.spacecraft import parts as P
from sq_mitsuba.data.spacecraft.grammar import BUS_MATERIALS, WING_STYLES, X, Y, Z, chance, pick
from sq_mitsuba.data.spacecraft.parts import Part

PART_GRAPH = "part_graph"
"""The recipe's name (the catalogue's ``archetype``)."""

MAX_TILT_DEG = 35.0
"""Largest angle between an attached body or dish and the normal of the face it stands on."""
MAX_REACH_DEG = 70.0
"""Largest angle between a boom or an array and the normal of the face it leaves from (so
its root reaches well into the host)."""

_SIDES = (4, 4, 3, 6, 8, 32)  # 4: a box
_PANEL_MATERIALS = ("white_paint", "silver_mli", "solar_cell", "aluminium")
_INSTRUMENT_MATERIALS = ("white_paint", "silver_mli", "gold_mli", "aluminium")

Attachment = Callable[[np.random.Generator, G.Site, np.ndarray, np.ndarray, float, float],
                      tuple[list[Part], G.Body | None]]
"""``(rng, site, direction, up, scale, thin) -> (parts, new host or None)``: ``up`` is the
attachment's second axis (an array's sun side, a panel's or a body's turn about its axis); it
turns with each copy, so copies are the same attachment turned."""

MIN_THICKNESS = 2.0
"""Smallest side of an attached body or instrument, in panel thicknesses (``thin``): sizes
shrink along a chain of hosts, and nothing thinner than a panel is worth a primitive."""


def _log_uniform(rng: np.random.Generator, low: float, high: float) -> float:
    """A value between ``low`` and ``high`` > 0, uniform in its logarithm (one draw)."""
    return float(np.exp(rng.uniform(np.log(low), np.log(high))))


def _scale(body: G.Body) -> float:
    """A host's size for its attachments: its middle side."""
    return float(np.sort(body.size)[1])


def _random_body(rng: np.random.Generator, length: float, width: float, material: str,
                 center: np.ndarray, axis: np.ndarray, up: np.ndarray) -> G.Body:
    """A box or a prism (3-32 sides) ``length`` along ``axis`` and about ``width`` across,
    centred at ``center``, its local x turned towards ``up`` (two draws)."""
    sides = int(pick(rng, _SIDES))
    aspect = rng.uniform(0.6, 1.0)
    rotation = G.orient(Z, axis, X, up)
    if sides == 4:
        return G.box_body((width, width * aspect, length), material, "bus_box", center,
                          rotation)
    return G.prism_body(sides, width / 2, length, material, None, center, rotation)


def _standing_direction(site: G.Site, direction: np.ndarray,
                        most: float = MAX_TILT_DEG) -> np.ndarray:
    """``direction`` turned towards the site's normal until at most ``most`` degrees from
    it (a body, dish or instrument stands on the face, however the attachment was aimed)."""
    angle = float(np.degrees(np.arccos(np.clip(site.normal @ direction, -1.0, 1.0))))
    if angle <= most:
        return direction
    return G.turned(site.normal, direction, most)


def _body(rng: np.random.Generator, site: G.Site, direction: np.ndarray, up: np.ndarray,
          scale: float, thin: float) -> tuple[list[Part], G.Body | None]:
    """A body straight on the host, on a strut, or at the end of a truss."""
    how = pick(rng, ("direct", "direct", "strut", "truss"))
    length = max(scale * _log_uniform(rng, 0.4, 2.5), MIN_THICKNESS * thin)
    width = max(scale * _log_uniform(rng, 0.3, 1.1), MIN_THICKNESS * thin)
    gap = scale * _log_uniform(rng, 0.3, 2.5)
    material = pick(rng, BUS_MATERIALS)
    d = _standing_direction(site, direction)
    if how == "direct":
        sink = min(0.25 * length, site.embed())
        center = site.point + d * (length / 2 - sink)
        body = _random_body(rng, length, width, material, center, d, up)
        return list(body.parts), body
    # On a strut or a truss the body reaches back over the end, never to the host.
    overlap = min(0.2 * length, 0.5 * gap)
    if how == "strut":
        radius = G.rod_radius(0.06 * width, thin)
        strut, tip = G.boom_from(site, d, gap, radius, "strut")
        center = tip.point + d * (length / 2 - overlap)
        body = _random_body(rng, length, width, material, center, d, up)
        return strut + list(body.parts), body
    rod = G.rod_radius(0.015 * scale, thin)
    truss_width = max(min(0.35 * width, 0.3 * site.depth), 6 * rod)
    start = site.point - d * site.embed()
    end = site.point + d * gap
    frame = G.truss_between(start, end, truss_width, rod, max(1, round(gap / truss_width)), up)
    width = max(width, 2.5 * truss_width)
    center = end + d * (length / 2 - overlap)
    body = _random_body(rng, length, width, material, center, d, up)
    return frame + list(body.parts), body


def _boom(rng: np.random.Generator, site: G.Site, direction: np.ndarray, up: np.ndarray,
          scale: float, thin: float) -> tuple[list[Part], G.Body | None]:
    """A boom or mast 0.8-6 times the host: bare, with a sensor, or with a platform at the
    tip that later attachments may use."""
    tip_kind = pick(rng, ("bare", "sensor", "platform", "platform"))
    length = scale * _log_uniform(rng, 0.8, 6.0)
    radius = G.rod_radius(scale * _log_uniform(rng, 0.01, 0.05), thin)
    platform = scale * _log_uniform(rng, 0.2, 0.7)
    material = pick(rng, ("aluminium", "dark_composite", "gold_mli"))
    boom, tip = G.boom_from(site, _standing_direction(site, direction, MAX_REACH_DEG), length,
                            radius, "boom")
    if tip_kind == "bare":
        return boom, None
    if tip_kind == "sensor":
        size = max(4 * radius, 0.6 * platform)
        return boom + G.tip_block(tip, size, "white_paint", "sensor", up=up).parts, None
    block = G.tip_block(tip, max(platform, 4 * radius, MIN_THICKNESS * thin), material,
                        "platform", up=up)
    return boom + list(block.parts), block


def _wing(rng: np.random.Generator, site: G.Site, direction: np.ndarray, up: np.ndarray,
          scale: float, thin: float) -> tuple[list[Part], G.Body | None]:
    """An array of any style along ``direction``, 1-8 times the host, cells towards ``up``
    (canted by up to 30 degrees in a third of arrays)."""
    style = pick(rng, WING_STYLES)
    span = scale * _log_uniform(rng, 1.0, 8.0)
    chord = scale * rng.uniform(0.3, 1.2)
    panels = int(rng.integers(1, 6))
    yoke = scale * rng.uniform(0.05, 0.6)
    cant = rng.uniform(-30.0, 30.0) * float(chance(rng, 0.3))
    local = G.wing(rng, style, span, chord, panels, thin, yoke,
                   embed=site.embed(cap=0.3 * scale), cant_deg=cant)
    return G.wing_at(site, _standing_direction(site, direction, MAX_REACH_DEG), up, local), None


def _dish(rng: np.random.Generator, site: G.Site, direction: np.ndarray, up: np.ndarray,
          scale: float, thin: float) -> tuple[list[Part], G.Body | None]:
    """A dish 0.4-2.5 times the host, flush or on a mast up to 1.5 times the host."""
    diameter = scale * _log_uniform(rng, 0.4, 2.5)
    mast = scale * rng.uniform(0.0, 1.5) * float(chance(rng, 0.5))
    facing = _standing_direction(site, direction)
    material = pick(rng, ("antenna_white", "antenna_white", "gold_mli", "aluminium"))
    return G.dish_at(rng, site, diameter, thin, facing, mast, material), None


def _panel(rng: np.random.Generator, site: G.Site, direction: np.ndarray, up: np.ndarray,
           scale: float, thin: float) -> tuple[list[Part], G.Body | None]:
    """A flat panel (sunshade, radiator) flat on the face, up to 3 times the host, or a
    fin standing out of it, its length towards ``up``."""
    fin = chance(rng, 0.5)
    a = scale * _log_uniform(rng, 0.5, 3.0)
    b = scale * _log_uniform(rng, 0.3, 2.0)
    material = pick(rng, _PANEL_MATERIALS)
    if fin:  # standing out of the face, sunk a quarter of its height
        size = (a, 3 * thin, b)
        return G.box_on(site, size, material, "radiator", up=up,
                        sink=min(0.25 * b, site.embed())), None
    return G.box_on(site, (a, b, 2 * thin), material, "sunshade", up=up, sink=0.5 * thin), None


def _instrument(rng: np.random.Generator, site: G.Site, direction: np.ndarray, up: np.ndarray,
                scale: float, thin: float) -> tuple[list[Part], G.Body | None]:
    """A box with an aperture (standing on the face), a telescope tube or a cylinder (looking
    along the direction), 0.15-0.8 times the host."""
    kind = pick(rng, ("box", "tube", "cylinder"))
    s = np.maximum(scale * rng.uniform(0.15, 0.8, size=3), MIN_THICKNESS * thin)
    material = pick(rng, _INSTRUMENT_MATERIALS)
    look = _standing_direction(site, direction)
    if kind == "box":
        return G.box_on(site, s, material, aperture=True, up=up), None
    if kind == "tube":
        tube = P.telescope_tube(s[0] * 0.5, s[2] * 2.0, thin, door=False, material=material)
        return G.mount(tube, site, Z, look, lift=-site.embed(cap=0.3 * s[2])), None
    return G.cylinder_on(site, s[0] * 0.5, s[2], material, "instrument", direction=look), None


ATTACHMENTS: dict[str, tuple[Attachment, float]] = {
    "body": (_body, 0.24), "boom": (_boom, 0.18), "wing": (_wing, 0.2), "dish": (_dish, 0.12),
    "panel": (_panel, 0.12), "instrument": (_instrument, 0.14),
}
"""Each kind of attachment: its builder and the probability that an attachment is of it."""


def _aim(rng: np.random.Generator, host: G.Body, main: np.ndarray) -> np.ndarray:
    """A direction out of ``host`` (body frame): along the spacecraft's main axis, either
    way (40 %), along one of the host's six axes (35 %), both tilted up to 10 degrees, or
    any direction (25 %); seven draws every time. The main axis is what makes most part
    graphs long and flat, as spacecraft with arrays and booms are."""
    axis = host.axis([X, -X, Y, -Y, Z, -Z][int(rng.integers(6))])
    sign = 1.0 if chance(rng, 0.5) else -1.0
    u = rng.random()
    tilted = G.tilted(rng, sign * main if u < 0.4 else axis, 10.0)
    anywhere = G.unit(rng.normal(size=3))
    return tilted if u < 0.75 else anywhere


def _copies(rng: np.random.Generator, local: np.ndarray) -> list[np.ndarray]:
    """The rotations (host frame) of an attachment's copies: one, two opposite (a half turn
    about the host axis farthest from the direction), or 3-4 turns about that axis (two
    draws)."""
    layout = pick(rng, ("single", "pair", "ring"), (0.4, 0.45, 0.15))
    count = {"single": 1, "pair": 2, "ring": int(rng.integers(3, 5))}[layout]
    axis = [X, Y, Z][int(np.argmin(np.abs(local)))]
    return [P.rotation_about(axis, 360.0 * k / count) for k in range(count)]


def part_graph(rng: np.random.Generator, thin: float) -> list[Part]:
    """A spacecraft as a random tree of attachments on a core body (see the module)."""
    core_length = _log_uniform(rng, 0.5, 3.0)
    core_width = _log_uniform(rng, 0.6, 1.6)
    core_axis = pick(rng, (X, Y, Z))
    # Half the cores square with the body axes, half turned about their own axis.
    spin = rng.uniform(0.0, 360.0) * float(chance(rng, 0.5))
    core_up = P.rotation_about(core_axis, spin) @ G.perpendicular(core_axis)
    core = _random_body(rng, core_length, core_width, pick(rng, BUS_MATERIALS), np.zeros(3),
                        core_axis, core_up)
    main = pick(rng, (X, Y, Z))
    hosts = [core]
    parts = list(core.parts)
    names = list(ATTACHMENTS)
    weights = [weight for _, weight in ATTACHMENTS.values()]
    for _ in range(int(rng.integers(2, 11))):
        # The core takes a little more than half of the attachments: p = 0.5 + 0.5 / hosts.
        on_core = chance(rng, 0.5)
        index = int(rng.integers(len(hosts)))
        host = core if on_core else hosts[index]
        kind = pick(rng, names, weights)
        local = host.rotation.T @ _aim(rng, host, main)
        up_local = host.rotation.T @ G.tilted(rng, host.axis(G.perpendicular(local)), 180.0)
        shift = rng.uniform(-0.35, 0.35, size=3)
        copies = _copies(rng, local)
        sub_seed = int(rng.integers(2**32))
        for turn in copies:
            direction = host.axis(turn @ local)
            up = host.axis(turn @ up_local)
            # Turned offsets can leave the box a little (a third of a turn): held inside.
            inside = np.clip(turn @ shift, -0.35, 0.35) * host.size
            site = host.toward(direction, host.rotation @ inside)
            new_parts, new_host = ATTACHMENTS[kind][0](
                np.random.default_rng(sub_seed), site, direction, up, _scale(host), thin)
            parts += new_parts
            if new_host is not None:
                hosts.append(new_host)
    return parts
