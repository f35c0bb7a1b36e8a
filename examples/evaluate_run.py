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
    print(f"PSNR {m.psnr:.2f} dB  SSIM {m.ssim:.3f}  AUSE-MAE {m.ause_mae:.3f}  NLL {m.nll:.3f}  calibration error "
          f"{m.calibration_error:.3f}")
    print(f"{metrics.seconds_per_view:.2f} s per view for K = {metrics.num_samples} samples")
    report.run([run], run / "report", ReportConfig())  # (it prints where it wrote the page)


if __name__ == "__main__":
    if not 2 <= len(sys.argv) <= 3:
        sys.exit(__doc__ + f"\nGive RUN, and optionally K ({len(sys.argv) - 1} arguments given).")
    if len(sys.argv) == 3 and not (sys.argv[2].isdigit() and int(sys.argv[2]) >= 1):
        sys.exit(__doc__ + f"\nK must be a whole number of samples, 1 or more, not {sys.argv[2]}.")
    try:
        main(Path(sys.argv[1]), int(sys.argv[2]) if len(sys.argv) > 2 else 10)
    except UserError as err:  # a wrong path or an unfinished run: the message, not a traceback
        sys.exit(f"error: {err.render()}")
