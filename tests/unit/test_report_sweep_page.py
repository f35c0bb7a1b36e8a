"""The sweep page (``report.sweep_page``) on ``SweepSummary`` models, as ``stages.sweep`` passes it.

Replaces ``tests/unit/test_sweep_page.py``, which called the page with hand-made dicts.
"""

import re

from uncertsplat.report.sweep_page import build_sweep_page
from uncertsplat.schemas import SweepRecord, SweepSummary


def _rec(pid, method, time, ause, default=False, status="ok") -> SweepRecord:
    r = dict(id=pid, hash=f"h{pid}", job="j0", method=method, knobs={"iterations": 100}, is_default=default,
             status=status, run_dir=f"runs/{pid}")
    if status == "ok":
        r.update(time=time, ause_mae=ause, psnr=20.0, nll=float("nan"), train_seconds=time, peak_memory_mb=10.0)
    else:
        r.update(stage="train", error="RuntimeError: boom")
    return SweepRecord(**r)


def _summary(recs, pareto, default) -> SweepSummary:
    return SweepSummary(name="t", spec={}, num_points=len(recs), num_failed=sum(r.status != "ok" for r in recs),
                        default=default, pareto_x="time", pareto=pareto, records=recs)


def test_page_marks_front_and_default_and_lists_failures(tmp_path):
    recs = [_rec("a", "variational", 10.0, 0.3, default=True), _rec("b", "fisher", 5.0, 0.5),
            _rec("c", "ensemble", 50.0, 0.6), _rec("d", "paper", 0, 0, status="failed")]
    summary = _summary(recs, {"ause_mae_vs_time": ["b", "a"]}, "a")
    summary = SweepSummary.read(summary.write(tmp_path / "sweep.json"))  # what a reader of sweep.json gets
    page = build_sweep_page(summary, "pareto.png")
    row = {pid: re.search(rf'<tr [^>]*data-point="{pid}">(.*?)</tr>', page, re.S) for pid in "abcd"}
    assert all(row.values())
    assert "★" in row["a"].group(1) and "front" in row["a"].group(1)
    assert "front" in row["b"].group(1) and "front" not in row["c"].group(1)
    assert 'data-key="ause_mae" data-value="0.6"' in row["c"].group(1)
    assert "boom" in row["d"].group(1)  # the failed point is listed with its error
    assert "<td>-</td>" in row["a"].group(1)  # NaN NLL (stored as null) shows as '-', not 'nan'
    assert 'src="pareto.png"' in page


def test_page_without_points_says_so():
    page = build_sweep_page(_summary([], {}, None), None)
    assert "No point has finished" in page and "<img" not in page


def test_page_shows_the_table_over_seeds_per_scene(tmp_path):
    from uncertsplat.sweep.pareto import summarize
    from uncertsplat.sweep.spec import SweepSpec

    recs = []
    for scene in ("a", "b"):
        for seed, (t, ause) in enumerate([(10.0, 0.3), (12.0, 0.5)]):
            r = _rec(f"{scene}.variational_seed{seed}", "variational", t, ause, default=True)
            recs.append(r.model_copy(update={"scene": scene, "seed": seed}))
    spec = SweepSpec(scenes={"a": {"synth": {}}, "b": {"synth": {}}}, seeds=[0, 1])
    summary = SweepSummary.read(summarize(spec, recs).write(tmp_path / "sweep.json"))
    page = build_sweep_page(summary, "pareto.png")
    row = re.search(r'<tr [^>]*data-group="a.variational">(.*?)</tr>', page, re.S).group(1)
    assert "0.4000 ± 0.1414" in row and 'data-key="ause_mae" data-value="0.4"' in row
    assert "★" in row and "front" in row and "0, 1" in row
    point = re.search(r'<tr [^>]*data-point="b.variational_seed1">(.*?)</tr>', page, re.S).group(1)
    assert "front" in point  # a seed's record is marked when its point (over seeds) is on the front
    single = build_sweep_page(_summary([_rec("a", "variational", 1.0, 0.1, default=True)], {}, "a"), None)
    assert 'id="sweep-table"' not in single  # one scene, one seed: the points table says it all


def test_knobs_the_spec_never_set_are_not_listed():
    """A knob the spec leaves unset is None in the record (the configs' own value): the page listed
    "num_entries=None, downscale=None, ..." beside each point."""
    rec = _rec("a", "variational", 10.0, 0.3, default=True)
    rec.knobs = {"iterations": 100, "num_entries": None, "downscale": None}
    page = build_sweep_page(_summary([rec], {}, "a"), "pareto.png")
    row = re.search(r'<tr [^>]*data-point="a">(.*?)</tr>', page, re.S).group(1)
    assert "iterations=100" in row and "None" not in row


def test_page_names_the_points_whose_growth_memory_held():
    from uncertsplat.strategy.budget import memory_hold_warning

    warning = memory_hold_warning({"step": 100, "gaussians": 4324, "budget": 50000, "room_mb": 200.0,
                                   "per_gaussian_bytes": 6144})
    held = _rec("b", "variational", 5.0, 0.5).model_copy(update={"notes": [f"training: {warning}", "other"]})
    page = build_sweep_page(_summary([_rec("a", "variational", 10.0, 0.3), held], {}, None), None)
    assert "growth in the training of b:" in page
    free = build_sweep_page(_summary([_rec("a", "variational", 10.0, 0.3)], {}, None), None)
    assert "Memory held" not in free


def test_a_sweep_point_s_record_notes_memory_holding_its_training_or_a_member_s():
    from uncertsplat.strategy.budget import memory_hold_warning
    from uncertsplat.sweep.jobs import held_notes

    warning = memory_hold_warning({"step": 100, "gaussians": 4324, "budget": 50000, "room_mb": 200.0,
                                   "per_gaussian_bytes": 6144})
    assert held_notes([warning, "the model fits its photos poorly"]) == [f"training: {warning}"]
    assert held_notes([f"member 2: {warning}"]) == [f"training: member 2: {warning}"], "an ensemble's member"
    assert held_notes(["scene: a photo was turned"]) == []
