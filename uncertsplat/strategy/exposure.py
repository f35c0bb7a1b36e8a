"""When to learn each photo's exposure: ``TrainConfig.exposure = "auto"`` switches it on once the photos are seen to
differ in brightness.

Learning a gain and an offset per training photo (``render.exposure``) is what photos taken with automatic exposure
need (the synthetic scene with photo gains of log-std 0.25: held-out 22.98 -> 24.10 dB), and a cost where the photos
share one exposure (the same scene as generated: -0.37 dB over three seeds; BENCHMARKS.md, "Photos of different
exposure"). Whether a capture needs it is measured, as the SH bands and the model's growth are:

every ``exposure_check_interval`` steps from ``EXPOSURE_CHECK_FROM`` to ``EXPOSURE_CHECK_UNTIL`` of the run, a few
training photos are compared with the model's deterministic render, and each photo's gain relative to it is fitted by
least squares (``render.exposure.fitted_gain``, per channel with an offset, mean over the channels). When the brightest of them is
``EXPOSURE_SPREAD`` times the darkest or more, the photos' exposures are learned from the next step on (every photo
at the identity at first); otherwise the next test looks again. The tests draw no random numbers, so a run whose
tests never fire trains exactly as with ``exposure = "off"``.

Measured (8 photos per test): the demo scene at 160x120 as generated 1.047 / 1.012 / 1.008 at steps 250 / 500 / 750;
with photo gains of log-std 0.25, 2.43 at step 250 and 2.31 at step 500 (fired); bonsai 1.33 at step 250 and 1.23 at
step 1500 (fired), though a model trained on it without exposures reproduces its photos within 1.077 at the end.
So the test cannot tell bonsai's differences (its learned gains span 0.87-1.11) from a capture's exposure, and
``auto`` is not the default (BENCHMARKS.md, "Photos of different exposure").
"""

from __future__ import annotations

from uncertsplat.schemas.runs import ExposureCheck

EXPOSURE_SPREAD = 1.15
"""The ratio of the largest to the smallest fitted gain over the tested photos from which their exposures are learned
(``exposure = "auto"``) or ``train`` warns (``"off"``)."""
EXPOSURE_CHECK_FROM = 0.2
"""Exposure tests start at this fraction of the iterations: a model that has barely started to fit its photos
reproduces some of them brighter than others without their exposures differing (bonsai: gains spread 1.33 at step
250 of 7000, 1.077 at the end)."""
EXPOSURE_CHECK_UNTIL = 0.5
"""Exposure tests run up to this fraction of the iterations: later, the Gaussians have fitted what they could of the
photos' differences, and learning the exposures would have little left to take over."""


def exposure_check_due(step: int, cfg, enabled: bool) -> bool:
    """Whether the exposure test runs after ``step`` (a ``TrainConfig``; ``enabled``: the exposures are learned
    already)."""
    if cfg.exposure != "auto" or enabled or step <= 0 or step % cfg.exposure_check_interval:
        return False
    return EXPOSURE_CHECK_FROM * cfg.iterations <= step <= EXPOSURE_CHECK_UNTIL * cfg.iterations


def gain_spread(gains: list[float]) -> float:
    """The largest over the smallest of ``gains`` (1 for fewer than two, or a gain that is not positive)."""
    if len(gains) < 2 or min(gains) <= 0.0:
        return 1.0
    return max(gains) / min(gains)


def exposure_reason(check: ExposureCheck) -> str:
    """One line for the log: the test's numbers and what was decided."""
    verdict = (f">= {check.threshold:g}: learning each photo's exposure from here on" if check.enabled
               else f"< {check.threshold:g}: the photos share one exposure so far")
    return (f"exposure test at step {check.step}: the {check.views} training photos tested have gains "
            f"{check.gain_min:.3f}-{check.gain_max:.3f} relative to the model's render (spread {check.spread:.3f} "
            f"{verdict})")


__all__ = ["EXPOSURE_CHECK_FROM", "EXPOSURE_CHECK_UNTIL", "EXPOSURE_SPREAD", "ExposureCheck", "exposure_check_due",
           "exposure_reason", "gain_spread"]
