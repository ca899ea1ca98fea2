"""Tests of the configuration style (:mod:`sq_mitsuba.config`)."""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

import pytest

from sq_mitsuba.config import (
    ConfigError,
    apply_overrides,
    bounds,
    config_hash,
    describe,
    field_docs,
    from_dict,
    in_range,
    load,
    non_negative,
    positive,
    save,
    to_dict,
    to_toml,
    validate,
)


@dataclass(frozen=True)
class SunConfig:
    enabled: bool = True
    """Whether the scene is lit by the sun."""
    irradiance: float = positive(1361.0)
    """Solar irradiance in W/m^2."""
    direction: tuple[float, float, float] = (0.0, 0.0, 1.0)
    """Direction towards the sun.

    This second paragraph is left out of describe().
    """


@dataclass(frozen=True)
class PoseConfig:
    distance_scale: tuple[float, float] = field(default=(1.0, 1.2), metadata=bounds(1, 10))
    """Range of camera distances, in object radii."""
    views: int = field(default=4, metadata=bounds(1, None))
    """Views per object."""
    elevation_deg: float | None = None
    """Fixed elevation in degrees, or None for random ones."""

    def __post_init__(self) -> None:
        if self.distance_scale[0] > self.distance_scale[1]:
            raise ValueError("distance_scale: the first value exceeds the second")


@dataclass(frozen=True)
class SceneConfig:
    sun: SunConfig = field(default_factory=SunConfig)
    """Lighting."""
    background: Literal["black", "stars"] = "black"
    """What is behind the spacecraft."""


@dataclass(frozen=True)
class RunConfig:
    name: str = "run"
    """Name of the run."""
    lr: float = in_range(0.0, 1.0, default=1e-3, low_inclusive=False)
    """Learning rate."""
    steps: int = non_negative(100)
    """Optimisation steps."""
    seeds: tuple[int, ...] = (0,)
    """Random seeds, one run each."""
    weights: dict[str, float] = field(default_factory=lambda: {"silhouette": 1.0, "overlap": 0.1})
    """Loss weights by term."""
    out_dir: Path = field(default=Path("runs"))
    """Where outputs go."""
    threshold: float = field(default=math.inf, metadata=bounds(allow_nonfinite=True))
    """Stop when the loss falls below this."""
    tag: str | None = None
    """Optional label."""
    scene: SceneConfig = field(default_factory=SceneConfig)
    pose: PoseConfig = field(default_factory=PoseConfig)
    """Camera poses."""


@dataclass(frozen=True)
class Required:
    size: int
    """No default: must be given."""


def custom() -> RunConfig:
    """A config whose every field differs from its default."""
    return RunConfig(
        name='space "1"\n',
        lr=0.25,
        steps=7,
        seeds=(1, 2, 3),
        weights={"silhouette": 2.0, "solar panel": 0.5},
        out_dir=Path("out/a b"),
        threshold=1e-4,
        tag="x",
        scene=SceneConfig(
            sun=SunConfig(enabled=False, irradiance=2.5, direction=(1.0, 0.0, -1e-9)),
            background="stars",
        ),
        pose=PoseConfig(distance_scale=(2.0, 3.5), views=9, elevation_deg=-12.5),
    )


def error(func: Callable[..., object], *args: object) -> str:
    """The message of the ConfigError that ``func(*args)`` raises (always one line)."""
    with pytest.raises(ConfigError) as info:
        func(*args)
    message = str(info.value)
    assert "\n" not in message
    return message


# --- from_dict / to_dict ---------------------------------------------------------------------


def test_missing_keys_take_defaults():
    assert from_dict(RunConfig, {}) == RunConfig()
    config = from_dict(RunConfig, {"scene": {"sun": {"irradiance": 5}}, "out_dir": "x/y"})
    assert config.scene.sun == SunConfig(irradiance=5.0)
    assert isinstance(config.scene.sun.irradiance, float)
    assert config.out_dir == Path("x/y")
    assert config.pose == PoseConfig()


def test_round_trip_through_plain_data():
    config = custom()
    data = to_dict(config)
    assert json.loads(json.dumps(data)) == data  # JSON-able as is
    assert data["seeds"] == [1, 2, 3]
    assert data["out_dir"] == "out/a b"
    assert data["scene"]["sun"]["direction"] == [1.0, 0.0, -1e-9]
    assert from_dict(RunConfig, data) == config
    assert from_dict(RunConfig, to_dict(RunConfig())) == RunConfig()


@pytest.mark.parametrize("suffix", [".json", ".toml"])
def test_round_trip_through_files(tmp_path, suffix):
    for config in (custom(), RunConfig()):
        path = tmp_path / f"config{suffix}"
        save(config, path)
        assert load(RunConfig, path) == config
        assert load(RunConfig, str(path)) == config


def test_load_hand_written_toml_and_json(tmp_path):
    toml = tmp_path / "run.toml"
    toml.write_text(
        'name = "fit"  # a comment\n'
        "seeds = [4, 5]\n"
        "[pose]\n"
        "distance_scale = [1, 2.5]\n"
        "[scene.sun]\n"
        "enabled = false\n"
    )
    expected = RunConfig(
        name="fit",
        seeds=(4, 5),
        pose=PoseConfig(distance_scale=(1.0, 2.5)),
        scene=SceneConfig(sun=SunConfig(enabled=False)),
    )
    assert load(RunConfig, toml) == expected
    js = tmp_path / "run.json"
    js.write_text(json.dumps(to_dict(expected)))
    assert load(RunConfig, js) == expected


def test_none_for_optional_fields():
    config = from_dict(RunConfig, {"tag": None, "pose": {"elevation_deg": 30}})
    assert config.tag is None
    assert config.pose.elevation_deg == 30.0
    assert error(from_dict, RunConfig, {"name": None}) == "name: expected a string, got null"


def test_toml_refuses_null_when_default_is_not_null():
    @dataclass(frozen=True)
    class Tagged:
        tag: str | None = "default"

    assert to_toml(Tagged(tag="x")) == 'tag = "x"\n'
    with pytest.raises(ConfigError, match="cannot be written exactly as TOML"):
        to_toml(Tagged(tag=None))


# --- strictness -----------------------------------------------------------------------------


def test_unknown_key_names_the_dotted_path():
    message = error(from_dict, RunConfig, {"scene": {"sun": {"irradiance": 1.0, "enabld": True}}})
    assert message.startswith(
        "scene.sun.enabld: unknown key; expected one of: enabled, irradiance, direction"
    )
    assert "did you mean 'enabled'?" in message
    assert error(from_dict, RunConfig, {"nme": "x"}).startswith("nme: unknown key;")


def test_wrong_types():
    cases = {
        "scene.sun.irradiance: expected a number, got 'x'": {"scene": {"sun": {"irradiance": "x"}}},
        "steps: expected an integer, got 3.0": {"steps": 3.0},
        "scene.sun.enabled: expected a boolean, got 1": {"scene": {"sun": {"enabled": 1}}},
        "name: expected a string, got 5": {"name": 5},
        "seeds[1]: expected an integer, got 'b'": {"seeds": [1, "b"]},
        "scene.background: expected one of 'black', 'stars', got 'grey'": {
            "scene": {"background": "grey"}
        },
        "pose: expected a table of PoseConfig fields, got 3": {"pose": 3},
        "weights.overlap: expected a number, got 'x'": {"weights": {"overlap": "x"}},
        "out_dir: expected a path (string), got 3": {"out_dir": 3},
        "tag: expected a string or null, got 1": {"tag": 1},
        "scene.sun.direction: expected a list of 3 numbers, got [0, 1] (length 2)": {
            "scene": {"sun": {"direction": [0, 1]}}
        },
    }
    for expected, data in cases.items():
        assert error(from_dict, RunConfig, data) == expected
    assert error(from_dict, RunConfig, [1]) == "expected a table of RunConfig fields, got [1]"


def test_bool_is_not_an_integer_nor_a_number():
    assert error(from_dict, RunConfig, {"steps": True}) == "steps: expected an integer, got true"
    assert error(from_dict, RunConfig, {"lr": False}) == "lr: expected a number, got false"
    assert from_dict(RunConfig, {"lr": 1}).lr == 1.0  # an integer is a fine float


def test_non_finite_numbers():
    assert error(from_dict, RunConfig, {"lr": math.nan}) == "lr: expected a finite number, got nan"
    message = error(from_dict, RunConfig, {"pose": {"distance_scale": [1.0, math.inf]}})
    assert message == "pose.distance_scale[1]: expected a finite number, got inf"
    assert from_dict(RunConfig, {"threshold": math.inf}).threshold == math.inf  # allowed there
    assert math.isnan(from_dict(RunConfig, {"threshold": math.nan}).threshold)


def test_missing_required_key():
    assert error(from_dict, Required, {}) == "size: missing required key"
    assert from_dict(Required, {"size": 3}) == Required(3)


def test_post_init_errors_are_prefixed_with_the_path():
    message = error(from_dict, RunConfig, {"pose": {"distance_scale": [3, 2]}})
    assert message == "pose: distance_scale: the first value exceeds the second"


def test_config_error_is_a_value_error():
    assert issubclass(ConfigError, ValueError)


# --- bounds ---------------------------------------------------------------------------------


def test_bounds_in_from_dict():
    message = error(from_dict, RunConfig, {"pose": {"distance_scale": [1.0, 20]}})
    assert message == "pose.distance_scale[1]: expected a value in [1, 10], got 20"
    assert error(from_dict, RunConfig, {"lr": 0}) == "lr: expected a value in (0, 1], got 0"
    assert error(from_dict, RunConfig, {"steps": -1}) == "steps: expected a value >= 0, got -1"
    assert error(from_dict, RunConfig, {"pose": {"views": 0}}) == (
        "pose.views: expected a value >= 1, got 0"
    )
    message = error(from_dict, RunConfig, {"scene": {"sun": {"irradiance": -1.5}}})
    assert message == "scene.sun.irradiance: expected a value > 0, got -1.5"
    assert from_dict(RunConfig, {"lr": 1, "pose": {"distance_scale": [1, 10]}}).lr == 1.0


def test_validate_configs_built_in_code():
    validate(RunConfig())
    validate(custom())
    bad = RunConfig(pose=PoseConfig(distance_scale=(0.5, 1.0)))
    assert error(validate, bad) == "pose.distance_scale[0]: expected a value in [1, 10], got 0.5"
    bad = RunConfig(scene=SceneConfig(sun=SunConfig(irradiance=math.nan)))
    assert error(validate, bad) == "scene.sun.irradiance: expected a finite number, got nan"
    assert error(validate, RunConfig(seeds=[1, 2])) == (  # type: ignore[arg-type]
        "seeds: expected a list of integers, got [1, 2] (a tuple in code: (1, 2))"
    )
    validate(RunConfig(lr=1))  # an int for a float is fine in code too


def test_invalid_defaults_are_reported():
    @dataclass(frozen=True)
    class Bad:
        x: float = positive(0.0)

    assert error(from_dict, Bad, {}) == "x: expected a value > 0, got 0"


def test_bounds_arguments_are_checked():
    with pytest.raises(ValueError, match="above high"):
        bounds(2, 1)
    with pytest.raises(ValueError, match="finite"):
        bounds(math.nan, 1)


# --- files ----------------------------------------------------------------------------------


def test_field_errors_in_files_name_the_file(tmp_path):
    path = tmp_path / "space.json"
    path.write_text(json.dumps({"scene": {"sun": {"irradiance": "x"}}}))
    message = error(load, RunConfig, path)
    assert message == f"{path}: scene.sun.irradiance: expected a number, got 'x'"


def test_missing_file(tmp_path):
    path = tmp_path / "absent.toml"
    assert error(load, RunConfig, path) == f"{path}: no such file"


def test_malformed_files(tmp_path):
    toml = tmp_path / "bad.toml"
    toml.write_text('name = "ok"\nsteps = = 3\n')
    message = error(load, RunConfig, toml)
    assert message.startswith(f"{toml}: malformed TOML:")
    assert "line 2" in message
    js = tmp_path / "bad.json"
    js.write_text('{\n  "name": "ok",\n  "steps": }\n')
    message = error(load, RunConfig, js)
    assert message.startswith(f"{js}: malformed JSON at line 3")
    js.write_text("[1, 2]")
    assert error(load, RunConfig, js) == f"{js}: expected a JSON object at the top, got list"
    js.write_text('{"steps": 1, "steps": 2}')
    assert error(load, RunConfig, js) == f"{js}: duplicate key 'steps'"
    js.write_text("[" * 100_000 + "]" * 100_000)  # deeper than the parser's stack
    assert error(load, RunConfig, js) == f"{js}: malformed JSON: nested too deeply"
    toml.write_text("a = " + "[" * 100_000 + "]" * 100_000)
    assert error(load, RunConfig, toml) == f"{toml}: malformed TOML: nested too deeply"
    other = tmp_path / "run.yaml"
    other.write_text("steps: 1")
    assert error(load, RunConfig, other).startswith(f"{other}: unsupported config file type")


# --- hashing --------------------------------------------------------------------------------


def test_config_hash():
    digest = config_hash(RunConfig())
    assert re.fullmatch(r"[0-9a-f]{16}", digest)
    assert config_hash(RunConfig()) == digest
    assert config_hash(from_dict(RunConfig, to_dict(RunConfig()))) == digest
    assert config_hash(RunConfig(lr=1)) == config_hash(RunConfig(lr=1.0))
    assert config_hash(RunConfig(steps=101)) != digest
    nested = RunConfig(scene=SceneConfig(sun=SunConfig(irradiance=1361.5)))
    assert config_hash(nested) != digest


# --- overrides ------------------------------------------------------------------------------


def test_overrides():
    base = RunConfig()
    config = apply_overrides(
        base,
        [
            "pose.distance_scale=[1.5,2]",
            "scene.sun.enabled=false",
            'name="abc"',
            "lr=3e-4",
            "seeds = [3, 4]",
            "scene.background=stars",
            "out_dir=results/today",
            "weights.overlap=0.5",
            "tag=null",
            "pose.elevation_deg=10",
        ],
    )
    assert config == replace(
        base,
        pose=PoseConfig(distance_scale=(1.5, 2.0), elevation_deg=10.0),
        scene=SceneConfig(sun=SunConfig(enabled=False), background="stars"),
        name="abc",
        lr=3e-4,
        seeds=(3, 4),
        out_dir=Path("results/today"),
        weights={"silhouette": 1.0, "overlap": 0.5},
    )
    assert base == RunConfig()  # untouched
    assert apply_overrides(base, ["name=abc def"]).name == "abc def"  # bare strings
    assert apply_overrides(base, ["name=123"]).name == "123"
    assert apply_overrides(base, ["name=steps=2"]).name == "steps=2"
    assert apply_overrides(base, ["steps=1", "steps=2"]).steps == 2  # later wins
    sun = apply_overrides(base, ["scene.sun={irradiance=5}"]).scene.sun
    assert sun == SunConfig(irradiance=5.0)


def test_override_errors_name_the_key():
    base = RunConfig()
    cases = {
        "scene.sun.enabled=maybe": (
            "scene.sun.enabled: expected a boolean, got 'maybe' (not a TOML value)"
        ),
        "steps=1.5": "steps: expected an integer, got 1.5",
        "pose.distance_scale=[1.0]": (
            "pose.distance_scale: expected a list of 2 numbers, got [1.0] (length 1)"
        ),
        "pose.distance_scale=[1.0, 20.0]": (
            "pose.distance_scale[1]: expected a value in [1, 10], got 20"
        ),
        "lr=nan": "lr: expected a finite number, got nan",
        "weights.overlap=x": "weights.overlap: expected a number, got 'x' (not a TOML value)",
        "pose.distance_scale=[3, 2]": (
            "pose.distance_scale: distance_scale: the first value exceeds the second"
        ),
        "steps.x=1": "steps.x: steps is an integer; it has no sub-keys",
        "weights.a.b=1": "weights.a.b: weights.a is a number; it has no sub-keys",
        "tag.x=1": "tag.x: tag is a string or null; it has no sub-keys",
    }
    for override, expected in cases.items():
        assert error(apply_overrides, base, [override]) == expected
    message = error(apply_overrides, base, ["scene.sun.phase_deg=3"])
    assert message.startswith("scene.sun.phase_deg: unknown key; expected one of: enabled")
    assert error(apply_overrides, base, ["pose.elevation_deg.x=3"]).startswith(
        "pose.elevation_deg.x:"
    )
    assert "override 'steps': no '='; expected steps=VALUE" in error(apply_overrides, base,
                                                                     ["steps"])
    assert "expected KEY=VALUE" in error(apply_overrides, base, ["scene..sun=1"])
    with pytest.raises(TypeError):
        apply_overrides(base, "steps=1")


# --- documentation --------------------------------------------------------------------------


def test_field_docs():
    docs = field_docs(RunConfig)
    assert docs["lr"] == "Learning rate."
    assert docs["pose"] == "Camera poses."
    assert "scene" not in docs  # undocumented
    assert field_docs(SunConfig)["direction"] == (
        "Direction towards the sun.\n\nThis second paragraph is left out of describe()."
    )
    assert list(field_docs(SunConfig)) == ["enabled", "irradiance", "direction"]

    @dataclass(frozen=True)
    class Local:
        a: int = 1
        """Doc of a,
        on two lines."""
        b: int = 2

    assert field_docs(Local) == {"a": "Doc of a,\non two lines."}


def test_describe_lists_every_field_with_its_default():
    text = describe(RunConfig)
    lines = text.splitlines()
    assert len(lines) == 15
    by_name = {line.split(" = ")[0]: line for line in lines}
    assert list(by_name)[-5:] == [
        "scene.sun.direction",
        "scene.background",
        "pose.distance_scale",
        "pose.views",
        "pose.elevation_deg",
    ]
    assert re.fullmatch(
        r"pose\.distance_scale = \[1\.0, 1\.2\] +# Range of camera distances, in object radii\. "
        r"\(in \[1, 10\]\)",
        by_name["pose.distance_scale"],
    )
    assert by_name["name"].startswith('name = "run" ')
    assert by_name["lr"].endswith("# Learning rate. (in (0, 1])")
    assert by_name["scene.sun.enabled"].startswith("scene.sun.enabled = true ")
    assert by_name["scene.sun.direction"].endswith("# Direction towards the sun.")
    assert by_name["scene.background"].endswith("(one of 'black', 'stars')")
    assert by_name["weights"].startswith("weights = {silhouette = 1.0, overlap = 0.1} ")
    assert by_name["threshold"].startswith("threshold = inf ")
    assert by_name["tag"].startswith("tag = null ")
    assert by_name["out_dir"].startswith('out_dir = "runs" ')
    assert 'name = "abc"' in describe(apply_overrides(RunConfig(), ["name=abc"]))
    assert describe(Required).startswith("size = <required>")


def test_describe_values_are_valid_overrides():
    config = custom()
    overrides = [line.split("  #")[0].strip() for line in describe(config).splitlines()]
    rebuilt = apply_overrides(RunConfig(), overrides)
    assert rebuilt == config
