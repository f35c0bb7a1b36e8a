"""Config schemas: round trip, unknown keys, ranges, NaN/Inf, overrides."""

import json

import pytest

from uncertsplat.config import (
    STAGE_CONFIGS,
    EvalConfig,
    KeyLines,
    PruneConfig,
    TrainConfig,
    build_config,
    load_toml,
    parse_override,
    toml_key_lines,
    train_config_from,
)
from uncertsplat.errors import UserError


@pytest.mark.parametrize("name", sorted(k for k in STAGE_CONFIGS if k != "pipeline"))
def test_round_trip_json(name):
    model = STAGE_CONFIGS[name]
    cfg = model()
    again = model.model_validate(json.loads(cfg.model_dump_json()))
    assert again == cfg


def test_unknown_key_is_named():
    with pytest.raises(UserError, match="iteratons: unknown key"):
        build_config(TrainConfig, {"iteratons": 5})


def test_nested_unknown_key_is_named():
    with pytest.raises(UserError, match=r"densify\.intervall"):
        build_config(TrainConfig, {"densify": {"intervall": 5}})


def test_early_runs_with_random_background_false_load_as_today():
    """The earliest runs wrote `random_background = false` (an option named before it was built); it is the
    default of the option built since (TrainConfig.random_background)."""
    old_run = json.loads(TrainConfig().model_dump_json()) | {"random_background": False}
    assert build_config(TrainConfig, old_run) == TrainConfig()
    for key in ("depth_scale", "residual_scale"):  # "auto" | a number: true is neither
        with pytest.raises(UserError, match=rf"{key}: true/false given where a number is expected"):
            build_config(EvalConfig, {key: True})
    assert build_config(EvalConfig, {"residual_leverage": True}).residual_leverage == "full"  # a legacy bool, read
    assert build_config(TrainConfig, {"random_background": True}).random_background is True


@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_nan_inf_rejected(value):
    with pytest.raises(UserError):
        build_config(EvalConfig, {"std_floor": value})


def test_range_checked():
    with pytest.raises(UserError, match="num_samples"):
        build_config(EvalConfig, {"num_samples": 0})


@pytest.mark.parametrize("override, match", [
    ({"fisher": {"params": []}}, "fisher.params"),  # it trained the whole model, then failed at the Fisher pass
    ({"seed": 2**64}, "seed"),  # a traceback from torch's generator (an ensemble: after some members trained)
    ({"seed": 2**32 - 7}, "seed"),  # the trainer's seed + 5 must stay below 2**32
    ({"seed": 2**32}, "seed"),  # torch's CPU generator keeps the low 32 bits: the same model as seed 0
])
def test_training_settings_that_could_only_fail_later_are_refused(override, match):
    from uncertsplat.config import TrainConfig

    with pytest.raises(UserError, match=match):
        build_config(TrainConfig, override)
    # the bound itself is taken, and a run stored with settings that trained (an init_opacity below the pruning
    # threshold, which densification need not reach) still loads
    build_config(TrainConfig, {"seed": 2**32 - 8, "init_opacity": 0.004})
    # an ensemble's last member takes seed + ensemble_size - 1: refused up front (member 1 failed after member 0)
    with pytest.raises(UserError, match=r"the last, 4294967297, is over 4294967288 .* at most 4294967279"):
        build_config(TrainConfig, {"method": "ensemble", "seed": 2**32 - 8})
    build_config(TrainConfig, {"method": "ensemble", "seed": 2**32 - 17})  # 10 members: the last at 2**32 - 8


def test_prune_modes_exclusive():
    with pytest.raises(UserError, match="only one"):
        build_config(PruneConfig, {"keep_ratio": 0.5, "auto": True})


def test_override_parsing():
    assert parse_override("a.b=3") == {"a": {"b": 3}}
    assert parse_override("x=0.5") == {"x": 0.5}
    assert parse_override("name=hello") == {"name": "hello"}
    assert parse_override("flag=true") == {"flag": True}
    with pytest.raises(UserError):
        parse_override("novalue")


def test_preset_then_overrides():
    cfg = train_config_from("tiny", {"seed": 3}, ["iterations=7", "densify.interval=10"])
    assert cfg.iterations == 7 and cfg.seed == 3 and cfg.densify.interval == 10
    assert cfg.sh_degree == 1  # from the preset
    with pytest.raises(UserError, match="unknown preset"):
        train_config_from("nope")


def test_toml_errors_name_the_file(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("iterations = = 3")
    with pytest.raises(UserError, match="bad.toml"):
        load_toml(bad)
    with pytest.raises(UserError, match="not found"):
        load_toml(tmp_path / "missing.toml")


def test_an_unknown_key_gets_the_closest_valid_ones():
    """A typo names the key it probably meant (nested too); a key like none lists the valid keys at its level."""
    with pytest.raises(UserError, match=r"densify\.untill: unknown key \(did you mean densify\.until\?\)"):
        build_config(TrainConfig, {"densify": {"untill": 3}}, source="x.toml")
    with pytest.raises(UserError, match="iteratons: unknown key .did you mean iterations"):
        build_config(TrainConfig, {"iteratons": 3})
    with pytest.raises(UserError, match="zzzz: unknown key .check the spelling.; valid keys here: .*num_samples"):
        build_config(EvalConfig, {"zzzz": 3})


def test_a_rule_over_several_keys_is_said_without_an_internal_location():
    """A model validator's message (``prune --keep-ratio 0.8 --auto``) read "(root): give only one of keep_ratio,
    threshold, auto": no "(root)", and the options' names."""
    from uncertsplat.config import PruneConfig

    with pytest.raises(UserError) as info:
        build_config(PruneConfig, {"keep_ratio": 0.8, "auto": True}, source="the command line")
    text = info.value.render()
    assert "(root)" not in text and "give only one of --keep-ratio, --threshold and --auto" in text


def test_a_background_of_other_than_three_numbers_says_so():
    from uncertsplat.config import train_config_from

    for value in ("[1,1]", "[1,1,1,1]"):
        with pytest.raises(UserError, match=r"scene.background: give 3 numbers \(R, G, B\) in \[0, 1\]"):
            train_config_from("tiny", None, [f"scene.background={value}"])
    assert train_config_from("tiny", None, ["scene.background=[1,1,1]"]).scene.background == (1.0, 1.0, 1.0)


def test_seeds_beyond_what_the_generators_take_are_refused_by_name():
    """synth's and reconstruct's seeds had no upper bound: 2**31 failed inside pycolmap's RANSAC options, 1e15 in
    torch's manual_seed (tracebacks)."""
    from uncertsplat.config import ReconstructConfig, SynthConfig

    with pytest.raises(UserError, match="seed: Input should be less than or equal to 4294967295"):
        build_config(SynthConfig, {"seed": 10**15})
    with pytest.raises(UserError, match="seed: Input should be less than or equal to 2147483627"):
        build_config(ReconstructConfig, {"seed": 2**31})
    assert build_config(ReconstructConfig, {"seed": 2**31 - 21}).seed == 2**31 - 21
    with pytest.raises(UserError, match="init_num_random: Input should be less than or equal to 2000000"):
        build_config(TrainConfig, {"init_num_random": 10**12})
    from uncertsplat.config import EvalConfig  # a depth factor below float32's range made every depth 0

    with pytest.raises(UserError, match="depth_scale: .*greater than or equal to 0.000000000000000000000000000001"):
        build_config(EvalConfig, {"depth_scale": 1e-300})


def test_a_key_of_another_command_names_that_command():
    """A setting given to the wrong command (the README lists train's and evaluate's side by side) says whose it is
    instead of "check the spelling"; the valid keys are listed once however many keys are wrong."""
    with pytest.raises(UserError, match=r"ssim_cache_mb: not a setting of this command: `ssim_cache_mb` is one of "
                                        r"`uncertsplat train`'s \(uncertsplat train \.\.\. --set ssim_cache_mb="):
        build_config(EvalConfig, {"ssim_cache_mb": 0})
    with pytest.raises(UserError, match=r"num_samples: .* `uncertsplat evaluate`'s") as info:
        build_config(TrainConfig, {"num_samples": 4, "resolution": 0, "zzzz": 1})
    assert str(info.value).count("valid keys here") == 1 and "zzzz: unknown key (check the spelling)" in str(info.value)
    with pytest.raises(UserError, match="did you mean ssim_cache_mb"):  # a typo of this command's key stays one
        build_config(TrainConfig, {"ssim_cache_m": 0})
    # another command's key that looks like one of this command's: the other command first (keep_ratio given to
    # train read as a misspelt iterations)
    with pytest.raises(UserError, match=r"keep_ratio: not a setting of this command: .*`uncertsplat prune`'s .*; or "
                                        r"did you mean iterations\?"):
        build_config(TrainConfig, {"keep_ratio": 0.9})


def test_a_list_of_bare_names_is_a_list():
    """`--set scene.train_names=[a.png,b.png]` (the shell took the quotes, or none were typed) is the list of those
    names, not a string pydantic refuses as "not a valid list"; numbers in such a list stay numbers."""
    from uncertsplat.config import SceneConfig, parse_override

    assert parse_override("scene.train_names=[view_002.png, view_004.png]") == {
        "scene": {"train_names": ["view_002.png", "view_004.png"]}}
    assert parse_override('scene.train_names=["a.png","b.png"]')["scene"]["train_names"] == ["a.png", "b.png"]
    assert parse_override("x=[1, b.png, true]")["x"] == [1, "b.png", True]
    assert parse_override("name=001.png")["name"] == "001.png"
    cfg = build_config(SceneConfig, parse_override("train_names=[view_002.png,view_004.png]"))
    assert cfg.train_names == ["view_002.png", "view_004.png"]


def test_each_key_s_line_in_a_toml_file(tmp_path):
    """The line finder on a hand-built file: tables, arrays of tables (by index), dotted and quoted keys, comments,
    a multi-line array and string whose contents look like keys, inline tables (their keys on the parent's line)."""
    text = "\n".join([
        'name = "x"   # a = 1',                     # 1
        "[[stages]]",                                # 2
        'stage = "train"',                           # 3
        "config = { iterations = 5, densify = { until = 3 } }",  # 4
        "[[stages]]  # the second",                  # 5
        "stage = 'evaluate'",                        # 6
        "[stages.config]",                           # 7
        "num_samples = [",                           # 8
        "  1, 2,  # seed = 3",                       # 9
        "]",                                         # 10
        'note = """',                                # 11
        "seed = 4",                                  # 12
        '"""',                                       # 13
        'scene.downscale = 2.0',                     # 14
        '"quoted key" . inner = 1',                  # 15
        "[ densify ]",                               # 16
        "until = 1",                                 # 17
    ])
    lines = toml_key_lines(text)
    assert lines["name"] == 1 and lines["stages.0"] == 2 and lines["stages.0.stage"] == 3
    assert lines["stages.0.config"] == 4 and "stages.0.config.iterations" not in lines
    assert lines["stages.1.stage"] == 6 and lines["stages.1.config"] == 7 and lines["stages.1.config.num_samples"] == 8
    assert "seed" not in str(sorted(lines)) and lines["stages.1.config.note"] == 11
    assert lines["stages.1.config.scene.downscale"] == 14 and lines["stages.1.config.quoted key.inner"] == 15
    assert lines["densify"] == 16 and lines["densify.until"] == 17 and "a" not in lines
    # a key below one the file writes is found on its parent's line; a replaced key (--set) on none
    (tmp := tmp_path / "p.toml").write_text(text)
    where = KeyLines(tmp, prefix="stages.0.config")
    assert where.line("densify.until") == 4 and where.line("iterations") == 4
    assert KeyLines(tmp).line("densify.until") == 17 and KeyLines(tmp).line("nothing") is None
    assert KeyLines(tmp, replaced={"densify"}).line("densify.until") is None
    assert KeyLines(tmp.with_name("gone.toml")).line("name") is None  # the file gone: no line, no error
    # a multi-line string closed by four quotes (the fourth is the string's), escaped quotes in quoted keys
    assert toml_key_lines('a = ["""\nx""""]\nb = 1\n') == {"a": 1, "b": 3}
    assert toml_key_lines('"a\\"b" = 1\nc = 2\n') == {'a"b': 1, "c": 2}
    assert toml_key_lines('["x\\"y"]\nk = 1\n[z]\nk = 2\n')["z.k"] == 4
    # a line of this finder's never names a key tomllib does not read the same way
    import tomllib
    data = tomllib.loads(text)
    assert data["stages"][1]["config"]["num_samples"] == [1, 2] and data["densify"]["until"] == 1


def test_validation_errors_give_the_line_of_the_key(tmp_path):
    """Each key's line in the error, after the key; a key named by its option gets none."""
    path = tmp_path / "t.toml"
    path.write_text("iterations = -1\n[densify]\nuntill = 5\n")
    with pytest.raises(UserError, match=r"iterations \(line 1\): Input should be .*; densify\.untill \(line 3\): "
                                        r"unknown key \(did you mean densify\.until\?\)"):
        build_config(TrainConfig, load_toml(path), source=str(path), where=KeyLines(path))
    with pytest.raises(UserError, match=r"--iterations: Input should be"):
        build_config(TrainConfig, {"iterations": -1}, source=str(path), names={"iterations": "--iterations"},
                     where=KeyLines(path))


def test_true_or_false_is_not_taken_for_a_number():
    """pydantic reads true as 1: `num_samples = true` evaluated with K = 1 without a word. A number field (or a list
    of numbers) refuses true/false; a bool field, and one that takes either, keep taking them."""
    from uncertsplat.sweep.spec import SweepSpec

    for model, data, key in ((EvalConfig, {"num_samples": True}, "num_samples"),
                             (TrainConfig, {"scene": {"downscale": False}}, "scene.downscale"),
                             (TrainConfig, {"scene": {"background": [True, 0, 0]}}, "scene.background")):
        with pytest.raises(UserError, match=rf"{key}: true/false given where a number is expected"):
            build_config(model, data)
    assert build_config(TrainConfig, {"random_background": True}).random_background is True
    assert build_config(TrainConfig, {"iterations": 5}).iterations == 5
    for data in ({"default": {"num_samples": True}}, {"axes": {"iterations": [100, False]}}):
        with pytest.raises(ValueError, match="true/false given where a number is expected"):
            SweepSpec.model_validate(data)


def test_a_fixed_scene_frame_is_a_scale_and_a_shift():
    """``scene.world_from_source`` (a run's own frame, written by no one but kept for a user): the normalisation only
    scales and shifts, and the cameras are moved by those alone; a turn gave NaN or unturned cameras without a word."""
    from uncertsplat.config import SceneConfig

    ok = [[0.25, 0, 0, 1.0], [0, 0.25, 0, -2.0], [0, 0, 0.25, 0.5], [0, 0, 0, 1]]
    assert SceneConfig(world_from_source=ok).world_from_source[1][3] == -2.0
    turn = [[0.0, -0.25, 0, 0], [0.25, 0.0, 0, 0], [0, 0, 0.25, 0], [0, 0, 0, 1]]
    for bad, match in ((turn, "scale by one positive number and shift"),
                       ([[-1.0, 0, 0, 0], [0, -1.0, 0, 0], [0, 0, -1.0, 0], [0, 0, 0, 1]], "positive"),
                       ([[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 1.0, 1]], "last row"),
                       ([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]], "4x4"),
                       ([[float("nan"), 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1]], "finite")):
        with pytest.raises(ValueError, match=match):
            SceneConfig(world_from_source=bad)


def test_training_steps_have_an_upper_bound_that_no_shipped_file_passes():
    """`--iterations 100000000000000000000` was taken (an ETA of 1e15 hours): iterations and the growth test's re-fit
    steps are at most MAX_ITERATIONS, said with what that is; no preset, pipeline or sweep spec shipped asks for more."""
    import tomllib

    from uncertsplat.config import MAX_ITERATIONS, SHIPPED, TRAIN_PRESETS

    assert train_config_from(None, {"iterations": MAX_ITERATIONS}).iterations == MAX_ITERATIONS
    for data in ({"iterations": 10**20}, {"densify": {"growth_refit_steps": MAX_ITERATIONS + 1}}):
        with pytest.raises(UserError) as err:
            train_config_from(None, data)
        said = str(err.value)
        assert "less than or equal to 1000000 (1,000,000 steps are already days of training" in said, said

    def steps(node, key=""):  # every number given to iterations or growth_refit_steps, in tables and axes' lists
        if isinstance(node, dict):
            return [n for k, v in node.items() for n in steps(v, k)]
        if isinstance(node, list):
            return [n for v in node for n in steps(v, key)]
        return [node] if key in ("iterations", "growth_refit_steps") and isinstance(node, int) else []

    found = steps(TRAIN_PRESETS) + [n for f in SHIPPED.glob("*.toml") for n in steps(tomllib.loads(f.read_text()))]
    assert found and max(found) <= MAX_ITERATIONS
