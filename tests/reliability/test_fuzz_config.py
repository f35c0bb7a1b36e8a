"""Property-based fuzzing of configuration input: dicts, TOML files, ``--set`` overrides and the CLI.

Every input either validates or raises ``UserError`` naming the key; never another exception (a traceback).
"""

from __future__ import annotations

import math

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from uncertsplat.config import (
    STAGE_CONFIGS,
    PipelineConfig,
    build_config,
    load_toml,
    parse_override,
    train_config_from,
)
from uncertsplat.errors import UserError

FAST = settings(max_examples=60, deadline=2000, suppress_health_check=[HealthCheck.too_slow])

scalars = st.one_of(
    st.none(), st.booleans(), st.integers(-(2**70), 2**70), st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([math.nan, math.inf, -math.inf, 0, -1, 1e308, "nan", "inf", "", "auto", "tiny", "cuda"]),
    st.text(max_size=12),
)
values = st.recursive(scalars, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                       st.dictionaries(st.text(max_size=8), inner, max_size=3)),
                      max_leaves=8)


def _keys(model) -> list[str]:
    return list(model.model_fields)


@st.composite
def config_dicts(draw, model):
    """A dict over the model's real keys (and some unknown ones) with values of any type."""
    keys = _keys(model)
    chosen = draw(st.lists(st.sampled_from(keys), max_size=5, unique=True))
    data = {k: draw(values) for k in chosen}
    if draw(st.booleans()):
        data[draw(st.text(min_size=1, max_size=10))] = draw(values)
    return data


def _check(model, data):
    try:
        cfg = build_config(model, data, source="fuzz")
    except UserError as err:
        assert "invalid configuration in fuzz" in str(err)
        return None
    # whatever validates must be finite and round-trip through JSON (what RUN/config.json stores)
    again = build_config(model, __import__("json").loads(cfg.model_dump_json()), source="roundtrip")
    assert again == cfg
    return cfg


@FAST
@given(data=st.data())
def test_every_stage_config_validates_or_names_the_problem(data):
    name = data.draw(st.sampled_from(sorted(STAGE_CONFIGS)))
    model = STAGE_CONFIGS[name]
    _check(model, data.draw(config_dicts(model)))


@FAST
@given(key=st.sampled_from(["iterations", "lr.means_init", "scene.downscale", "variational.gate_temperature",
                            "densify.grad_threshold", "scene.background", "checkpoint_every", "seed"]),
       value=st.sampled_from(["nan", "inf", "-inf", "NaN", "1e999", "-1", "0", "[1, 2]", "{}", "\"x\"", "true"])
       | st.text(max_size=10))
def test_set_override_with_nan_inf_and_junk(key, value):
    try:
        cfg = train_config_from("tiny", None, [f"{key}={value}"])
    except UserError:
        return
    for v in (cfg.iterations, cfg.lr.means_init, cfg.scene.downscale, cfg.variational.gate_temperature,
              cfg.densify.grad_threshold, *cfg.scene.background):
        assert math.isfinite(v)


@FAST
@given(text=st.text(max_size=30))
def test_parse_override_never_crashes(text):
    try:
        out = parse_override(text)
    except UserError:
        return
    assert isinstance(out, dict) and len(out) == 1


@settings(max_examples=40, deadline=2000, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(raw=st.binary(max_size=200) | st.text(max_size=200).map(str.encode))
def test_toml_files_of_any_bytes(raw, tmp_path):
    p = tmp_path / "cfg.toml"
    p.write_bytes(raw)
    try:
        data = load_toml(p)
    except UserError as err:
        assert str(p) in str(err)
        return
    for model in (*STAGE_CONFIGS.values(), PipelineConfig):
        _check(model, data)


runner = CliRunner()


@settings(max_examples=15, deadline=10_000, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(sets=st.lists(st.sampled_from(["iterations=nan", "iterations=-5", "lr.means_init=inf", "bogus=1",
                                      "scene.downscale=0.5", "tile_size=1000", "densify=3", "variant=\"x\"",
                                      "seed=1e400", "scene.background=[2,0,0]", "=", "noequals",
                                      "scene.test_names=7", "keep_checkpoints=0"]), min_size=1, max_size=3))
def test_cli_train_with_bad_overrides_exits_2_without_traceback(sets, tmp_path):
    from uncertsplat.cli import app

    args = ["train", str(tmp_path / "no scene"), "-o", str(tmp_path / "run"), "--device", "cpu"]
    for s in sets:
        args += ["--set", s]
    res = runner.invoke(app, args)
    assert res.exit_code == 2, res.output
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    assert "Traceback" not in res.output
    assert not (tmp_path / "run").exists()  # nothing written for a refused command


@FAST
@given(text=st.text(alphabet=st.sampled_from(list("ab.=[]{}\"'#\n \t,1")), max_size=80))
def test_the_line_finder_reads_any_text(text):
    """The line finder runs in error paths only: on any text (not TOML, unbalanced brackets or quotes) it gives a
    line within the text or none, never an exception that would hide the error it serves."""
    from uncertsplat.config import toml_key_lines

    lines = toml_key_lines(text)
    assert all(1 <= n <= max(1, len(text.splitlines())) for n in lines.values())
