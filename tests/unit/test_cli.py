"""CLI wiring through Typer's test runner."""

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from uncertsplat import __version__
from uncertsplat.cli import app
from uncertsplat.console import q
from uncertsplat.errors import UserError

runner = CliRunner()


def test_version():
    result = runner.invoke(app, ["--version"])
    assert result.exit_code == 0
    assert __version__ in result.output


def test_help_lists_every_subcommand():
    result = runner.invoke(app, ["--help"])
    assert result.exit_code == 0
    for name in ["synth", "reconstruct", "train", "evaluate", "prune", "report", "run"]:
        assert name in result.output


def test_bad_device_is_a_clear_error(tmp_path):
    result = runner.invoke(app, ["train", str(tmp_path), "-o", str(tmp_path / "run"), "--device", "tpu"])
    assert result.exit_code == 2
    assert "unknown device" in result.output
    assert "Traceback" not in result.output


def test_python_dash_m_runs_the_same_cli():
    import subprocess
    import sys

    result = subprocess.run([sys.executable, "-m", "uncertsplat", "--version"], capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0, result.stderr
    assert __version__ in result.stdout
    result = subprocess.run([sys.executable, "-m", "uncertsplat", "--help"], capture_output=True, text=True,
                            timeout=120)
    assert "Usage: uncertsplat" in result.stdout


def test_numpy_is_imported_before_torch():
    """torch's C start-up imports numpy and swallows an error raised in it: a Ctrl-C landing there was lost (a
    helper's pipeline ran to its end after the interrupt, 3 times in 30). The CLI imports numpy first, in Python."""
    import subprocess
    import sys

    code = "import sys, uncertsplat.cli; print('numpy' in sys.modules and 'torch' not in sys.modules)"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.stdout.strip() == "True", result.stdout + result.stderr


def test_train_config_file_errors_name_the_file(tmp_path):
    """A typo in `train --config FILE` names FILE (as the other commands do); a typo in --set does not blame it."""
    bad = tmp_path / "tc_bad.toml"
    bad.write_text("iteratons = 100\n")
    result = runner.invoke(app, ["train", str(tmp_path), "-o", str(tmp_path / "run"), "--preset", "tiny",
                                 "--config", str(bad), "--device", "cpu"])
    assert result.exit_code == 2 and "Traceback" not in result.output
    out = result.output.replace("\n", "")
    assert str(bad) in out and "iteratons" in out, result.output
    good = tmp_path / "tc.toml"
    good.write_text("iterations = 100\n")
    result = runner.invoke(app, ["train", str(tmp_path), "-o", str(tmp_path / "run"), "--config", str(good),
                                 "--set", "seeed=1", "--device", "cpu"])
    assert result.exit_code == 2 and "seeed" in result.output and str(good) not in result.output.replace("\n", "")
    assert not (tmp_path / "run").exists()


def test_a_config_file_s_mistake_is_named_with_its_line(tmp_path):
    """`--config FILE` errors give the line of each key the file wrote (train's and another command's); a key an
    option or --set gave is named without a line of the file."""
    cfg = tmp_path / "t.toml"
    cfg.write_text("# settings\niterations = -1\n\n[densify]\nuntill = 5\n")
    result = runner.invoke(app, ["train", str(tmp_path), "-o", str(tmp_path / "run"), "--config", str(cfg),
                                 "--device", "cpu"])
    out = " ".join(result.output.split())
    assert result.exit_code == 2 and "iterations (line 2): Input should be" in out, result.output
    assert "densify.untill (line 5): unknown key (did you mean densify.until?)" in out
    cfg.write_text("num_samples = 0\nseed = 1\n")
    result = runner.invoke(app, ["evaluate", str(tmp_path), "--config", str(cfg)])
    assert "num_samples (line 1): Input should be" in " ".join(result.output.split()), result.output
    result = runner.invoke(app, ["evaluate", str(tmp_path), "--config", str(cfg), "--set", "num_samples=-1"])
    out = " ".join(result.output.split())
    assert result.exit_code == 2 and "num_samples: Input should be" in out and "(line" not in out, result.output


def test_depth_scale_that_is_neither_auto_nor_a_number(tmp_path):
    result = runner.invoke(app, ["evaluate", str(tmp_path), "--depth-scale", "foo", "--device", "cpu"])
    assert result.exit_code == 2 and "--depth-scale must be auto, scene or a number, not 'foo'" in result.output
    assert "literal" not in result.output


@pytest.mark.parametrize("value", ["-1", "0", "inf"])
def test_depth_scale_that_is_not_positive_is_refused_before_rendering(tmp_path, value):
    result = runner.invoke(app, ["evaluate", str(tmp_path), "--depth-scale", value, "--device", "cpu"])
    assert result.exit_code == 2 and f"--depth-scale must be a positive number, not {value}" in result.output


def test_help_shows_the_sweep_scenes_table_name():
    result = runner.invoke(app, ["sweep", "--help"])
    assert result.exit_code == 0 and "[scenes.NAME]" in result.output


def test_the_paper_variant_with_a_baseline_is_noted(tmp_path):
    """--variant paper changes only the variational model's tables: a baseline trained with it is told so."""
    result = runner.invoke(app, ["train", str(tmp_path / "nowhere"), "-o", str(tmp_path / "run"), "--method",
                                 "deterministic", "--variant", "paper", "--device", "cpu"])
    out = " ".join(result.output.split())
    assert "the deterministic baseline has none, so it changes nothing here" in out
    result = runner.invoke(app, ["train", str(tmp_path / "nowhere"), "-o", str(tmp_path / "run"), "--variant", "paper",
                                 "--device", "cpu"])
    assert "changes nothing" not in result.output


def test_a_method_that_other_options_take_back_is_noted(tmp_path):
    """--method paper sets variant = paper; --variant ours takes it back: the run trains ours, and says so. A method
    whose keys stand (vi-single, paper alone) gets no note."""
    def note(*args):
        result = runner.invoke(app, ["train", str(tmp_path / "nowhere"), "-o", str(tmp_path / "run"), *args,
                                     "--device", "cpu"])
        return " ".join(result.output.split())

    assert ("note: --method paper was overridden by other options (variant = 'ours'): this run trains method "
            "variational, variant ours" in note("--method", "paper", "--variant", "ours"))
    assert "overridden" not in note("--method", "vi-single") and "overridden" not in note("--method", "paper")
    # vi-single's one-entry SGD posterior taken back by --set (only method and variant were compared: no word)
    said = note("--method", "vi-single", "--set", "variational.num_entries=5")
    assert "--method vi-single was overridden by other options (variational.num_entries = 5)" in said
    assert "posterior sgd" in said


def test_tolerance_without_auto_is_refused(tmp_path):
    result = runner.invoke(app, ["prune", str(tmp_path), "-o", str(tmp_path / "p"), "--tolerance-db", "0.2",
                                 "--device", "cpu"])
    assert result.exit_code == 2 and "--tolerance-db only applies to --auto" in " ".join(result.output.split())


@pytest.mark.parametrize("command", ["evaluate", "select-views"])
def test_a_file_given_as_the_run_folder_is_named_a_file(tmp_path, command):
    f = tmp_path / "spec.toml"
    f.write_text("x = 1\n")
    result = runner.invoke(app, [command, str(f), "--device", "cpu"])
    assert result.exit_code == 2 and "this is a file, not a run folder" in " ".join(result.output.split())


def test_a_union_key_reads_as_one_key():
    """degrees_of_freedom is "fit", "gaussian" or a number >= 2.1: one message for the key, not pydantic's tags."""
    result = runner.invoke(app, ["evaluate", "nowhere", "--set", "degrees_of_freedom=1", "--device", "cpu"])
    flat = " ".join(result.output.split())
    assert result.exit_code == 2 and "degrees_of_freedom: Input should be 'fit' or 'gaussian', or input should be " \
        "greater than or equal to 2.1" in flat and "literal" not in flat and "constrained" not in flat


def test_a_config_file_with_a_stage_table_says_how_to_write_it(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text("[train]\niterations = 5\n")
    result = runner.invoke(app, ["train", str(tmp_path), "-o", str(tmp_path / "run"), "--config", str(f),
                                 "--device", "cpu"])
    flat = " ".join(result.output.split())
    assert result.exit_code == 2 and "the file holds a [train] table" in flat and "Remove the [train] line" in flat
    assert not (tmp_path / "run").exists()


def test_a_pipeline_file_or_a_folder_given_as_config_says_what_it_is(tmp_path):
    f = tmp_path / "p.toml"
    f.write_text('name = "x"\n[[stages]]\nstage = "train"\n')
    for config, expected, hint in ((f, "this is a pipeline file (it lists [[stages]])", f"uncertsplat run {q(f)}"),
                                   (tmp_path, "this is a folder, not a config file", "Give the path of a .toml file")):
        result = runner.invoke(app, ["train", str(tmp_path), "-o", str(tmp_path / "run"), "--config", str(config),
                                     "--device", "cpu"])
        flat = " ".join(result.output.split())
        assert result.exit_code == 2 and expected in flat and hint in flat, flat
        assert not (tmp_path / "run").exists()


def test_report_refuses_a_run_given_twice(tmp_path):
    (tmp_path / "r").mkdir()
    result = runner.invoke(app, ["report", str(tmp_path / "r"), str(tmp_path / "r" / "."), "-o", str(tmp_path / "o")])
    assert result.exit_code == 2 and "this run folder is given twice" in " ".join(result.output.split())


def test_a_bad_option_value_is_named_by_its_option(tmp_path):
    """``-n 0`` is reported as ``-n/--num-views``, the option the user typed; the same value through ``--set``
    keeps the config key the user typed there."""
    result = runner.invoke(app, ["select-views", str(tmp_path), "-n", "0"])
    assert result.exit_code != 0
    assert "-n/--num-views: Input should be greater than or equal to 1" in " ".join(result.output.split())
    result = runner.invoke(app, ["select-views", str(tmp_path), "--set", "num_views=0"])
    text = " ".join(result.output.split())
    assert "num_views: Input should be" in text and "--num-views" not in text


def test_view_addresses_are_checked_at_once_with_the_command_s_own_option(tmp_path):
    """A busy port is named with the option of the command that took it (train: --view-port) before any run folder
    exists; a malformed --host fails at once instead of being looked up as a name; port 0 still checks the host."""
    import socket

    from uncertsplat.errors import UserError
    from uncertsplat.view.server import check_port

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        result = runner.invoke(app, ["train", str(tmp_path), "-o", str(tmp_path / "run"), "--view", "--view-port",
                                     str(port), "--device", "cpu"])
        flat = " ".join(result.output.split())
        assert result.exit_code == 2 and f"--view-port {port + 1}" in flat and "--port" not in flat.replace(
            "--view-port", ""), flat
        assert not (tmp_path / "run").exists()
    for host in ("999.1.1.1", "1.2.3"):
        with pytest.raises(UserError, match="not a valid IP address"):
            check_port(host, 0)
    with pytest.raises(UserError, match="cannot listen on 10.255.255.1:0"):
        check_port("10.255.255.1", 0)
    check_port("127.0.0.1", 0)
    check_port("localhost", 0)


@pytest.mark.parametrize(("command", "words"), [("prune", "nothing was written"),
                                                ("run_pipeline", "the stages that finished are kept")])
def test_ctrl_c_says_what_was_kept(command, words, capsys, monkeypatch):
    """Ctrl-C in a command that does not say it itself: what it kept and what to run (it printed 'interrupted')."""
    import typer

    from uncertsplat import cli
    from uncertsplat.cli import _handle_errors

    monkeypatch.setitem(cli._STATE, "process", True)  # as `uncertsplat` itself runs

    def stop():
        raise KeyboardInterrupt

    stop.__name__ = command
    with pytest.raises(typer.Exit) as exit_:
        _handle_errors(stop)()
    assert exit_.value.exit_code == 130
    import signal

    # a second Ctrl-C while the interpreter shuts down is ignored (it printed torch's atexit traceback)
    assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    signal.signal(signal.SIGINT, signal.default_int_handler)
    said = capsys.readouterr()
    out = " ".join((said.out + said.err).split())
    assert out.startswith("interrupted: ") and words in out


def _read_only_locks(monkeypatch):
    """The lock file cannot be created, as in a folder made immutable (`chattr +i`: EPERM, even for root)."""
    import errno
    import os

    real = os.open

    def fake(path, *args, **kwargs):
        if str(path).endswith(".lock"):
            raise PermissionError(errno.EPERM, os.strerror(errno.EPERM), str(path))
        return real(path, *args, **kwargs)

    monkeypatch.setattr(os, "open", fake)


def test_a_folder_that_refuses_the_lock_file_gets_advice(tmp_path, monkeypatch):
    """`train SCENE -o RO`, `evaluate RORUN` and `train --resume` on a read-only (immutable) folder said only "cannot
    write here (Operation not permitted)": what to do is said, as for the other write errors."""
    from uncertsplat.io.atomic import run_lock

    (tmp_path / "RUN").mkdir()
    _read_only_locks(monkeypatch)
    with pytest.raises(UserError) as err:
        with run_lock(tmp_path / "RUN", "evaluate"):
            pass
    said = " ".join(err.value.render().split())
    assert "cannot write here (Operation not permitted)" in said, said
    assert "Make the folder writable, or write elsewhere: an output folder you can write to (-o), or a copy of the " \
           "run for a command that writes into it (evaluate, select-views, train --resume)" in said, said


def test_select_views_on_a_read_only_run_fails_before_scoring(tmp_path, monkeypatch):
    """`select-views` on a read-only run scored every candidate (minutes) before it failed to write its selection: the
    folder is tried first (the lock file, as evaluate takes it), and no folder is left behind."""
    import uncertsplat.baselines as baselines

    run = tmp_path / "run"
    run.mkdir()

    def scored(*args, **kwargs):
        raise AssertionError("the run was loaded and scored before its folder was tried")

    monkeypatch.setattr(baselines, "load_run", scored)
    _read_only_locks(monkeypatch)
    result = runner.invoke(app, ["select-views", str(run), "--device", "cpu"])
    said = " ".join(result.output.split())
    assert result.exit_code == 2 and "cannot write here (Operation not permitted)" in said, said
    assert "Make the folder writable" in said and not (run / "select").exists()


@pytest.mark.parametrize(("code", "command", "words", "not_words"), [
    (28, "prune", "Free some space or choose another output folder, then run again.", "--resume"),  # ENOSPC
    (13, "prune", "Choose an output folder you can write to, then run again.", "space"),  # EACCES
    (30, "sweep", "Choose an output folder you can write to", "space"),  # EROFS
    (28, "train", "(--resume continues the training run)", "you can write to"),
])
def test_a_file_system_error_gets_the_advice_of_its_kind(code, command, words, not_words, capsys, tmp_path):
    """A full disk asks for space, a read-only or forbidden folder for another folder; only train mentions --resume,
    and not for a run folder without its config yet (the training never began: --resume would fail there)."""
    import os

    import typer

    from uncertsplat.cli import _handle_errors

    def fail(output=None):
        raise OSError(code, os.strerror(code), "/out/x")

    fail.__name__ = command
    with pytest.raises(typer.Exit):
        _handle_errors(fail)()
    said = capsys.readouterr()
    out = " ".join((said.out + said.err).split())
    assert out.startswith("error: /out/x: ") and words in out and not_words not in out
    if command == "train":
        with pytest.raises(typer.Exit):
            _handle_errors(fail)(output=tmp_path / "new_run")
        said = capsys.readouterr()
        assert "--resume" not in said.out + said.err and "then run again." in " ".join(said.err.split())


@pytest.mark.parametrize(("command", "run", "words", "not_words"), [
    ("evaluate", "run", "copy the run folder to a disk with room and evaluate the copy", "another output folder"),
    ("train", "run", "then run the same command again with --resume", "then run again"),
    ("train", "resumed", "then run the same command again (from its last checkpoint", "with --resume"),
    ("train", "none", "Free some space or choose another output folder, then run again.", "--resume"),
    ("prune", "run", "Free some space or choose another output folder, then run again.", "--resume"),
])
@pytest.mark.parametrize("raised", ["WriteFailed", "OSError"])
def test_a_full_disk_gets_advice_that_works_for_its_command(command, run, words, not_words, raised, tmp_path, capsys):
    """The writer's "free some space or choose another output folder, then run again": evaluate has no output folder
    to choose (it writes into the run), and train run again without --resume is refused once its folder holds the
    run's config ("already exists. Add --resume"); a train whose folder was never written runs again as it was."""
    import errno
    import os

    import typer

    from uncertsplat.cli import _handle_errors
    from uncertsplat.errors import WriteFailed

    folder = tmp_path / "run"
    folder.mkdir()
    if run != "none":
        (folder / "config.json").write_text("{}")

    def fail(**kwargs):
        if raised == "OSError":
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(folder / "x"))
        raise WriteFailed("could not write the file: the disk is full; nothing was left half-written",
                          path=folder / "x", hint="Free some space or choose another output folder, then run again.",
                          space=True)

    fail.__name__ = command
    kwargs = {"run": folder} if command == "evaluate" else {"output": folder, "resume": run == "resumed"}
    with pytest.raises(typer.Exit):
        _handle_errors(fail)(**kwargs)
    said = capsys.readouterr()
    out = " ".join((said.out + said.err).split())
    if raised == "OSError" and run == "none":  # (the handler's own words for a bare OSError)
        words, not_words = "Free some space or choose another output folder, then run again", "with --resume"
    assert out.startswith(f"error: {folder / 'x'}: ") and words in out and not_words not in out, out


@pytest.mark.parametrize(("command", "option", "default"), [("reconstruct", "--max-image-size", "1600"),
                                                             ("reconstruct", "--mapping-attempts", "4"),
                                                             ("evaluate", "--num-samples", "10"),
                                                             ("train", "--iterations", "7000 without a preset")])
def test_help_shows_the_config_defaults(command, option, default):
    """Options that default to their stage config's value (None in the signature) show that value in --help."""
    import re

    res = CliRunner().invoke(app, [command, "--help"], env={"COLUMNS": "200"})
    line = next(x for x in res.output.splitlines() if option in x)
    assert re.search(rf"\[default: {re.escape(default)}\]", line), line


@pytest.mark.parametrize("args", [["train", "scene", "-o", "r", "--iterations", "5", "--set", "iterations=7"],
                                  ["train", "scene", "-o", "r", "--method", "deterministic", "--set", "method=ensemble"],
                                  ["evaluate", "run", "--num-samples", "2", "--set", "num_samples=3"],
                                  ["synth", "s", "--preset", "demo", "--set", "preset=tiny"],
                                  ["run", "p.toml", "-o", "o", "--device", "cpu", "--set", "device=cuda"]])
def test_an_option_and_a_set_with_two_values_are_refused(tmp_path, monkeypatch, args):
    """--set won without a word (`--method deterministic --set method=ensemble` trained an ensemble; `run` let
    --device win instead): two values for one key are refused before anything runs."""
    monkeypatch.chdir(tmp_path)
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 2 and "two values" in res.output, res.output
    assert list(tmp_path.iterdir()) == []


def test_an_option_and_a_set_that_agree_or_a_set_alone_pass(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for args in (["evaluate", "nowhere", "--num-samples", "2", "--set", "num_samples=2"],
                 ["evaluate", "nowhere", "--set", "num_samples=3"],
                 ["evaluate", "nowhere", "--depth-gt", "gt/", "--set", "depth_gt=gt/"]):  # (a path typed twice)
        res = CliRunner().invoke(app, args)
        assert "two values" not in res.output and "run folder not found" in " ".join(res.output.split()), res.output


def test_a_relative_path_in_a_config_file_is_read_from_the_file_s_folder(tmp_path, monkeypatch):
    """`depth_gt = "../scene/depth"` in cfgs/eval.toml: from the file's folder wherever the command runs (it was read
    from the current folder, and the error named --depth-gt); an absolute one is kept."""
    from uncertsplat.cli import _PATH_KEYS, _config_file

    (tmp_path / "cfgs").mkdir()
    (tmp_path / "cfgs" / "eval.toml").write_text('num_samples = 2\ndepth_gt = "../scene/depth"\n')
    (tmp_path / "cfgs" / "abs.toml").write_text(f'depth_gt = "{tmp_path / "elsewhere"}"\n')
    monkeypatch.chdir("/")
    assert _PATH_KEYS == ("depth_gt", "candidates", "masks", "init_ply", "init_ply_transform")
    (tmp_path / "cfgs" / "rec.toml").write_text('masks = "../masks"\n')  # reconstruct's masks likewise
    assert _config_file(tmp_path / "cfgs" / "rec.toml")["masks"] == str(tmp_path / "cfgs" / ".." / "masks")
    assert _config_file(tmp_path / "cfgs" / "eval.toml")["depth_gt"] == str(tmp_path / "cfgs" / ".." / "scene" / "depth")
    assert _config_file(tmp_path / "cfgs" / "abs.toml")["depth_gt"] == str(tmp_path / "elsewhere")


def test_installed_pipelines_and_specs_run_by_name(tmp_path, monkeypatch):
    """The pipelines and sweep specs ship inside the package (a pip install had none: `uncertsplat run
    pipelines/photos.toml` was 'config file not found'); a name, name.toml or the repository's pipelines/ path that
    is not there finds them; a file that is there wins; anything else lists the names."""
    import tomllib

    from uncertsplat.config import SHIPPED, shipped_file, shipped_names

    assert {"demo", "photos", "smoke", "tradeoff"} <= set(shipped_names())
    pyproject = tomllib.loads((Path(__file__).resolve().parents[2] / "pyproject.toml").read_text(encoding="utf-8"))
    assert "pipelines/*.toml" in pyproject["tool"]["setuptools"]["package-data"]["uncertsplat"]
    monkeypatch.chdir(tmp_path)
    for given in ("photos", "photos.toml", "pipelines/photos.toml"):
        assert shipped_file(given) == SHIPPED / "photos.toml"
    (tmp_path / "photos").mkdir()  # the user's photo folder of that name (`run photos --set photos=photos`)
    assert shipped_file("photos") == SHIPPED / "photos.toml"
    (tmp_path / "photos.toml").write_text("name = 'mine'\n")
    assert shipped_file("photos.toml") == Path("photos.toml")  # the user's own file first
    with pytest.raises(UserError, match=r"file not found \(did you mean photos\?\)\. The pipelines and sweep specs "
                                        r"installed with uncertsplat run by name: demo, "):
        shipped_file("elsewhere/photos.toml")
    result = runner.invoke(app, ["run", "nothere", "-o", str(tmp_path / "out")])
    assert result.exit_code == 2 and "pipelines installed with uncertsplat run by name: demo, photos, smoke (" in \
        " ".join(result.output.split())


def test_a_pipeline_and_a_sweep_spec_are_told_apart(tmp_path):
    """`run tradeoff` (a sweep spec) failed on every key and offered the sweep specs to `run` too: each command now
    names the other's file and the command that runs it, and offers its own names, with the nearest one."""
    from uncertsplat.config import shipped_file, shipped_names

    assert shipped_names("sweep") == ["tradeoff"] and "tradeoff" not in shipped_names("pipeline")
    with pytest.raises(UserError, match=r"this is a sweep spec, not a pipeline\. Run it with `uncertsplat sweep "
                                        r"tradeoff -o OUT`"):
        shipped_file("tradeoff", "pipeline")
    own = tmp_path / "mine.toml"
    own.write_text("name = 'mine'\n[[stages]]\nkind = 'synth'\n")
    with pytest.raises(UserError, match=r"this is a pipeline, not a sweep spec\. Run it with `uncertsplat run "):
        shipped_file(own, "sweep")
    assert shipped_file(own, "pipeline") == own
    typo = tmp_path / "typo.toml"  # a pipeline with a mistyped key is neither: its reader names the key
    typo.write_text("[[stage]]\nkind = 'synth'\n")
    assert shipped_file(typo, "pipeline") == typo and shipped_file(typo, "sweep") == typo
    result = runner.invoke(app, ["sweep", "tradof", "-o", str(tmp_path / "out")])
    said = " ".join(result.output.split())
    assert result.exit_code == 2 and "did you mean tradeoff?" in said and "run by name: tradeoff (" in said


def test_our_warnings_read_as_one_line(capsys):
    """A warning raised in uncertsplat's own code prints as `warning: ...` (Python's format added the file, line
    and source line); another package's keeps Python's format."""
    import warnings

    import uncertsplat
    from uncertsplat.cli import _plain_warnings

    saved, passed = warnings.showwarning, []
    try:
        warnings.showwarning = lambda message, category, filename, lineno, file=None, line=None: passed.append(
            (str(message), filename))  # what showed warnings before (Python's own, or pytest's)
        _plain_warnings()
        ours = str(Path(uncertsplat.__file__).parent / "native" / "__init__.py")
        warnings.showwarning("native CPU kernels unavailable", UserWarning, ours, 252)
        warnings.showwarning("theirs", UserWarning, "/elsewhere/mod.py", 3)
    finally:
        warnings.showwarning = saved
    err = capsys.readouterr().err
    assert "warning: native CPU kernels unavailable\n" in err and "native/__init__.py" not in err
    assert passed == [("theirs", "/elsewhere/mod.py")]


@pytest.mark.parametrize("command, flag, key, extra", [
    ("prune", "--no-dry-run", "dry_run", ["-o", "OUT", "--keep-ratio", "0.9"]),
    ("prune", "--no-auto", "auto", []),
    ("prune", "--no-sweep", "sweep", []),
    ("reconstruct", "--no-overwrite", "overwrite", ["-o", "WS"]),
    ("reconstruct", "--no-extend", "extend", ["-o", "WS"]),
    ("evaluate", "--no-paper-nll", "paper_nll", []),
])
def test_a_no_flag_overrides_a_config_file_s_true(tmp_path, monkeypatch, command, flag, key, extra):
    """`--no-X` counted as not given (stored as `flag or None`), so a --config file's `X = true` stood: a
    --no-overwrite rebuilt a workspace, a --no-dry-run did a dry run. Given, it wins; not given, the file's stands."""
    from uncertsplat.stages import evaluate, prune, reconstruct

    seen = {}
    module = {"prune": prune, "reconstruct": reconstruct, "evaluate": evaluate}[command]
    monkeypatch.setattr(module, "run", lambda *a, **k: seen.update(cfg=next(x for x in (*a, *k.values())
                                                                          if hasattr(x, key))))
    (tmp_path / "c.toml").write_text(f"{key} = true\n")
    folder = tmp_path / "in"
    folder.mkdir()
    args = [a.replace("OUT", str(tmp_path / "o")).replace("WS", str(tmp_path / "ws")) for a in extra]
    for given, expected in (([flag], False), ([], True)):
        res = runner.invoke(app, [command, str(folder), *args, "--config", str(tmp_path / "c.toml"), *given])
        assert res.exit_code == 0, res.output
        assert getattr(seen.pop("cfg"), key) is expected


def test_a_config_json_an_output_folder_holds_is_taken_by_config(tmp_path):
    """--config read TOML only, so no config.json an output folder holds could be given back to run the same settings
    ("not a valid TOML file ... line 1, column 1"); a .json file is read as JSON, its nulls kept as they were written."""
    from uncertsplat.cli import _config_file
    from uncertsplat.config import EvalConfig, TrainConfig, build_config, train_config_from

    cfg = train_config_from("tiny", None, ["iterations=123", "scene.test_names=[\"a.png\"]"])
    (tmp_path / "config.json").write_text(cfg.model_dump_json(indent=2))
    assert build_config(TrainConfig, _config_file(tmp_path / "config.json")) == cfg
    ev = EvalConfig(num_samples=3, max_views=None)
    (tmp_path / "eval.json").write_text(ev.model_dump_json())
    assert build_config(EvalConfig, _config_file(tmp_path / "eval.json")) == ev
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(UserError, match="not a valid JSON file"):
        _config_file(tmp_path / "bad.json")


def test_the_records_that_hold_settings_are_taken_by_config(tmp_path):
    """README says `--config` takes back reconstruct_report.json's `options`, selection.json's `settings` and a
    pipeline stage's manifest.json, but the whole record was read as settings ("mapping_attempts: Input should be a
    valid integer"): their settings are taken, selection.json's without what its score used."""
    from uncertsplat.cli import _config_file
    from uncertsplat.config import (
        ReconstructConfig,
        SelectConfig,
        TrainConfig,
        build_config,
        train_config_from,
    )
    from uncertsplat.schemas.select import Selection
    from uncertsplat.stages.manifest import start_manifest

    rec = ReconstructConfig(max_image_size=1600, mapping_attempts=3)
    report = {"schema_version": 3, "images_registered": 12, "mapping_attempts": [{"seed": 0}],
              "options": rec.model_dump(mode="json")}
    (tmp_path / "reconstruct_report.json").write_text(json.dumps(report))
    assert build_config(ReconstructConfig, _config_file(tmp_path / "reconstruct_report.json")) == rec
    sel = SelectConfig(num_views=3, gaps=0.25)
    record = Selection(run="r", score="fisher", candidates="unused", num_candidates=4, chosen=[], seconds=1.0,
                       seconds_per_candidate=0.25, settings={**sel.model_dump(mode="json"), "width": 96, "height": 72,
                                                             "noise_std": 0.04, "params": ["means"]})
    (tmp_path / "selection.json").write_text(record.model_dump_json())
    assert build_config(SelectConfig, _config_file(tmp_path / "selection.json")) == sel
    cfg = train_config_from("tiny", None, ["iterations=123"])
    manifest = start_manifest("train", "train", cfg.model_dump(mode="json"), {"synth": "abc"})
    (tmp_path / "manifest.json").write_text(manifest.model_dump_json())
    assert build_config(TrainConfig, _config_file(tmp_path / "manifest.json")) == cfg
    # a config.json with a key of those names is a config as it is
    plain = {"options": {"a": 1}, "x": 2}
    (tmp_path / "config.json").write_text(json.dumps(plain))
    assert _config_file(tmp_path / "config.json") == plain


def test_a_text_setting_given_a_number_says_to_quote_it(tmp_path):
    """`--set title=2024` is read as a number and refused as "Input should be a valid string" with no word on how to
    give the text 2024."""
    from uncertsplat.config import ReportConfig, build_config, parse_override

    with pytest.raises(UserError, match=r"""--set 'title="2024"', or title = "2024" in a file"""):
        build_config(ReportConfig, parse_override("title=2024"), source="command line")
    assert build_config(ReportConfig, parse_override('title="2024"')).title == "2024"


@pytest.mark.parametrize("alias, keys", [("vi-single", "variational.num_entries = 1"), ("paper", 'variant = "paper"')])
def test_a_method_shorthand_given_as_a_key_says_what_it_sets(tmp_path, alias, keys):
    """`--set method=vi-single` (or a pipeline's `method = "vi-single"`) was refused naming the four values of the key
    only; the option's shorthands are named with the keys they set. `--method` itself takes them."""
    from uncertsplat.config import TrainConfig, build_config

    with pytest.raises(UserError, match=f"'{alias}' is a shorthand of .uncertsplat train --method., not a value.*sets {keys}"):
        build_config(TrainConfig, {"method": alias})
    res = runner.invoke(app, ["train", str(tmp_path / "nowhere"), "-o", str(tmp_path / "r"), "--set", f"method={alias}"])
    assert res.exit_code == 2 and "is a shorthand of `uncertsplat train --method`" in " ".join(res.output.split())
    from uncertsplat.stages.train import resolve_config

    cfg = resolve_config(None, {}, alias, {}, None)
    assert cfg.method == "variational" and (cfg.variant == "paper" or cfg.variational.num_entries == 1)


CPU_OOM = ("[enforce fail at alloc_cpu.cpp:127] data. DefaultCPUAllocator: can't allocate memory: you tried to "
           "allocate 108000000 bytes. Error code 12 (Cannot allocate memory)")


def test_memory_that_ran_out_is_said_with_what_lowers_the_commands_use(tmp_path, monkeypatch):
    """train, evaluate and prune ended with the allocator's traceback and exit code 1 when memory ran out: one
    paragraph now, naming the command's knobs, exit code 2; other runtime errors are still raised (bugs)."""
    from uncertsplat.errors import out_of_memory
    from uncertsplat.stages import evaluate

    told = out_of_memory(RuntimeError(CPU_OOM), "train")
    assert "train ran out of the machine's memory (an allocation of 0.10 GiB failed)" in told.render()
    assert "--set scene.downscale=2" in told.render() and "--resume" in told.render()
    assert "GPU" in out_of_memory(RuntimeError("CUDA out of memory. Tried to allocate 2.00 GiB"), "evaluate").render()
    assert "residual_views" in out_of_memory(MemoryError(), "evaluate").render()
    assert out_of_memory(RuntimeError("shape mismatch"), "train") is None
    assert out_of_memory(ValueError("can't allocate memory"), "train") is None

    def boom(*a, **k):
        raise RuntimeError(CPU_OOM)

    monkeypatch.setattr(evaluate, "run", boom)
    (tmp_path / "r").mkdir()
    res = runner.invoke(app, ["evaluate", str(tmp_path / "r")])
    said = " ".join(res.output.split())
    assert res.exit_code == 2 and "error: evaluate ran out of the machine's memory" in said and "Traceback" not in said
    assert "--set consistency_views=16" in said

    def bug(*a, **k):
        raise RuntimeError("shape mismatch")

    monkeypatch.setattr(evaluate, "run", bug)
    res = runner.invoke(app, ["evaluate", str(tmp_path / "r")])
    assert res.exit_code == 1 and isinstance(res.exception, RuntimeError)


def test_an_impossible_allocation_is_a_bug_not_memory_that_ran_out():
    """`torch.empty(2**62)` read "ran out of the machine's memory (an allocation of 4294967296.00 GiB failed)"; a size
    no machine has is a size gone wrong, raised as a bug. CUDA's other wording is memory."""
    from uncertsplat.errors import out_of_memory

    huge = RuntimeError("[enforce fail at alloc_cpu.cpp:127] DefaultCPUAllocator: can't allocate memory: you tried to "
                        f"allocate {2**62} bytes. Error code 12 (Cannot allocate memory)")
    assert out_of_memory(huge, "train") is None
    assert out_of_memory(RuntimeError("CUDA error: out of memory"), "train") is not None
    told = out_of_memory(RuntimeError(CPU_OOM), "prune").render()
    assert "--set num_samples=4" in told and "--num-samples" not in told


def test_another_commands_config_file_is_named_in_one_sentence(tmp_path):
    """`evaluate RUN --config RUN/config.json` (train's) printed one clause for each of its ~40 keys: the file is named
    as that command's, with the file to give."""
    from uncertsplat.config import TrainConfig

    cfg = tmp_path / "config.json"
    cfg.write_text(TrainConfig().model_dump_json())
    result = runner.invoke(app, ["evaluate", str(tmp_path), "--config", str(cfg)])
    said = " ".join(result.output.split())
    assert result.exit_code == 2 and "this is `uncertsplat train`'s configuration" in said, said
    assert "RUN/eval/config.json" in said and said.count("not a setting of this command") == 0
    # a file of this command's keys with one stray key is still checked key by key
    cfg.write_text('{"num_samples": 4, "iterations": 100}')
    result = runner.invoke(app, ["evaluate", str(tmp_path), "--config", str(cfg)])
    assert "`iterations` is one of `uncertsplat train`'s" in " ".join(result.output.split())


@pytest.mark.parametrize("command", ["select-views", "view"])
def test_another_commands_config_file_names_select_views_and_view(tmp_path, command):
    """`select-views RUN --config RUN/config.json` said "35 of its keys are not settings of `this command`), not
    `this command`'s": the two commands that are no pipeline stage are named as the others are."""
    from uncertsplat.config import TrainConfig

    cfg = tmp_path / "config.json"
    cfg.write_text(TrainConfig().model_dump_json())
    result = runner.invoke(app, [command, str(tmp_path), "--config", str(cfg)])
    said = " ".join(result.output.split())
    assert result.exit_code == 2 and "this is `uncertsplat train`'s configuration" in said, said
    assert f"are not settings of `uncertsplat {command}`), not `uncertsplat {command}`'s" in said, said
    assert "this command" not in said, said


_SUMMARY = {"schema_version": 1, "method": "variational", "variant": "ours", "steps": 200, "seconds": 1.0,
            "sec_per_step": 0.01, "num_gaussians": 9, "num_carriers": 9, "peak_memory_mb": 1.0, "device": "cpu",
            "scene": "/s", "ensemble_size": None, "profile": None, "transients": None}
"""The top of a train_summary.json: keys that are settings too (ensemble_size, profile, transients) among them."""


def test_train_names_another_commands_file_given_to_config(tmp_path):
    """`train --config RUN/eval/config.json` repeated "not a setting of this command" for each of evaluate's keys and
    `train --config RUN/train_summary.json` listed type errors ("ensemble_size: Input should be a valid integer"); a
    record, a sweep spec or another command's configuration is named in one sentence, by any command."""
    from uncertsplat.config import SHIPPED, EvalConfig

    files = {"eval.json": EvalConfig().model_dump_json(), "train_summary.json": json.dumps(_SUMMARY),
             "metrics.json": json.dumps({"schema_version": 3, "split": "test", "per_view": [], "mean": {}})}
    for name, text in files.items():
        (tmp_path / name).write_text(text)
    told = {"eval.json": "this is `uncertsplat evaluate`'s configuration",
            "train_summary.json": "this is `uncertsplat train`'s summary of a training (train_summary.json), not a "
                                  "command's --config file",
            "metrics.json": "this is `uncertsplat evaluate`'s metrics (metrics.json), not a command's --config file"}
    for name, expected in told.items():
        result = runner.invoke(app, ["train", str(tmp_path), "-o", str(tmp_path / "run"), "--config",
                                     str(tmp_path / name)])
        said = " ".join(result.output.split())
        assert result.exit_code == 2 and expected in said, said
        assert "not a setting of this command" not in said and "Input should be" not in said, said
        assert "RUN/config.json" in said, said
    spec = SHIPPED / "tradeoff.toml"
    result = runner.invoke(app, ["evaluate", str(tmp_path), "--config", str(spec)])
    said = " ".join(result.output.split())
    assert result.exit_code == 2 and "this is a sweep spec, not a command's --config file" in said, said
    assert f"uncertsplat sweep {q(spec)} -o OUT" in said and "not a setting" not in said, said
    assert not (tmp_path / "run").exists()


def test_run_and_sweep_name_a_file_that_is_not_theirs(tmp_path):
    """`uncertsplat run RUN/train/manifest.json` and `uncertsplat sweep RUN/config.json` said "not a valid TOML file
    (Invalid statement (at line 1, column 1))": what the file is and what the command takes, in one sentence."""
    from uncertsplat.config import TrainConfig

    manifest = {"schema_version": 1, "stage": "train", "name": "train", "config": {}, "config_hash": "x",
                "input_hashes": {}, "started_at": "now", "status": "done"}
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    (tmp_path / "config.json").write_text(TrainConfig().model_dump_json())
    (tmp_path / "train.toml").write_text("iterations = 100\nseed = 3\n")
    (tmp_path / "model.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\n\xff\xfe")
    cases = ((["run", str(tmp_path / "manifest.json")],
              "this is a pipeline stage's record (manifest.json, written by `uncertsplat run`), not a pipeline (a "
              "TOML file that lists [[stages]])", "uncertsplat run photos -o OUT"),
             (["sweep", str(tmp_path / "config.json")],
              "this is `uncertsplat train`'s configuration, not a sweep spec", "uncertsplat sweep tradeoff -o OUT"),
             (["run", str(tmp_path / "model.ply")], "not a pipeline (a TOML file that lists [[stages]])",
              "demo, photos, smoke"),
             (["run", str(tmp_path / "train.toml")], "this is `uncertsplat train`'s configuration, not a pipeline",
              "Give it to that command's --config; `uncertsplat run` takes a pipeline file"))
    for args, expected, hint in cases:
        result = runner.invoke(app, [*args, "-o", str(tmp_path / "out")])
        said = " ".join(result.output.split())
        assert result.exit_code == 2 and expected in said and hint in said, said
        assert "Invalid statement" not in said, said


@pytest.mark.parametrize(("args", "said"), [
    (["train", "S", "-o", "R", "--iterations", "abc"], "error: Invalid value for '--iterations': Input should be a "
                                                       "valid integer, unable to parse string as an integer"),
    (["train", "S", "-o", "R", "--iteration", "10"],
     "error: No such option: --iteration (Possible options: --iterations)"),
    (["trian"], "error: No such command 'trian'. Did you mean 'train'?"),
])
def test_a_usage_error_outside_a_terminal_is_plain_lines(args, said, monkeypatch):
    """Typer printed a usage error in a box-drawn panel wrapped at 80 columns in a pipe and under TERM=dumb too, where
    our own errors are plain lines never broken at a width (README): one `error: ...` line and the usage there; the
    panel stays in a terminal."""
    import uncertsplat.cli as cli

    result = runner.invoke(app, args)
    lines = result.output.splitlines()
    assert result.exit_code == 2 and said in lines, result.output
    assert any(line.startswith("Usage: uncertsplat ") for line in lines), result.output
    assert "--help' for help." in lines[-1] and not any(c in result.output for c in "╭│╰"), result.output
    monkeypatch.setattr(cli, "_plain_output", lambda: False)
    result = runner.invoke(app, args)
    assert result.exit_code == 2 and "╭─ Error" in result.output, result.output


@pytest.mark.parametrize("given", [["--depth-gt", "gt"], ["--set", "depth_gt=gt"]])
def test_a_relative_depth_gt_is_recorded_from_the_current_folder(tmp_path, monkeypatch, given):
    """`evaluate RUN --depth-gt gt` wrote `depth_gt = "gt"` into RUN/eval/config.json, and `--config` reads a relative
    path there from that file's folder: `evaluate RUN --config RUN/eval/config.json` looked for RUN/eval/gt ("GT depth
    folder not found"). The path is made absolute from the folder the command ran in before anything uses it."""
    from uncertsplat.stages import evaluate

    seen = {}
    monkeypatch.setattr(evaluate, "run", lambda run, cfg, **k: seen.update(cfg=cfg))
    monkeypatch.chdir(tmp_path)
    (tmp_path / "gt").mkdir()
    res = runner.invoke(app, ["evaluate", "run", *given])
    assert res.exit_code == 0, res.output
    assert seen["cfg"].depth_gt == tmp_path / "gt"
    (tmp_path / "eval").mkdir()  # written back as evaluate writes it, then given to --config from another folder
    (tmp_path / "eval" / "config.json").write_text(seen["cfg"].model_dump_json(indent=2))
    monkeypatch.chdir("/")
    res = runner.invoke(app, ["evaluate", str(tmp_path / "run"), "--config", str(tmp_path / "eval" / "config.json")])
    assert res.exit_code == 0, res.output
    assert seen["cfg"].depth_gt == tmp_path / "gt"
