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
