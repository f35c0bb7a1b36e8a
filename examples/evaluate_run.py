"""Evaluate a trained run (uncertainty maps + metrics) and write its HTML report.

    python examples/evaluate_run.py RUN [K]    # e.g. example_out/run 4

Writes RUN/eval/metrics.json, RUN/eval/maps/ and RUN/report/index.html; prints the mean metrics.
"""

import sys
from pathlib import Path

from uncertsplat.config import EvalConfig, ReportConfig
from uncertsplat.device import resolve_device
from uncertsplat.errors import UserError
from uncertsplat.schemas.metrics import EvalReport
from uncertsplat.stages import evaluate, report


def main(run: Path, k: int) -> None:
    evaluate.run(run, EvalConfig(num_samples=k), device=resolve_device("auto"))
    metrics = EvalReport.read(run / "eval" / "metrics.json")
    m = metrics.mean
    print(f"PSNR {m.psnr}  SSIM {m.ssim}  AUSE-MAE {m.ause_mae}  NLL {m.nll}  calibration error {m.calibration_error}")
    print(f"{metrics.seconds_per_view} s per view for K = {metrics.num_samples} samples")
    print("report:", report.run([run], run / "report", ReportConfig()))


if __name__ == "__main__":
    if len(sys.argv) < 2 or (len(sys.argv) > 2 and not (sys.argv[2].isdigit() and int(sys.argv[2]) >= 1)):
        sys.exit(__doc__ + "\nK must be a whole number of samples, 1 or more.")
    try:
        main(Path(sys.argv[1]), int(sys.argv[2]) if len(sys.argv) > 2 else 10)
    except UserError as err:  # a wrong path or an unfinished run: the message, not a traceback
        sys.exit(f"error: {err.render()}")
