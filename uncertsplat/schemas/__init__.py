"""One pydantic model per JSON file uncertsplat writes, used both to write and to read it.

Every file carries ``schema_version``; ``Model.read(path)`` validates a file and fails with one message
that names the file and the key or version that is wrong (``schemas.base``). Nothing in the package
reads these files any other way.

=============================  =====================  ==========================
file                           written by             model
=============================  =====================  ==========================
WS/reconstruct_report.json     ``reconstruct``        :class:`ReconstructReport`
SCENE/scene.json               ``synth``              :class:`SynthScene`
RUN/scene.json                 ``train``              :class:`RunScene`
RUN/train_summary.json         ``train``              :class:`TrainSummary`
RUN/eval/metrics.json          ``evaluate``           :class:`EvalReport`
OUT/prune.json                 ``prune``              :class:`PruneReport`
OUT/sweep.json (prune)         ``prune --sweep``      :class:`PruneSweep`
STAGE/manifest.json            ``run`` (pipelines)    :class:`Manifest`
OUT/sweep.jsonl, sweep.json    ``sweep``              :class:`SweepRecord`, :class:`SweepSummary`
OUT/selection.json             ``select-views``       :class:`Selection`
=============================  =====================  ==========================
"""

from uncertsplat.schemas.base import SchemaFile, Strict
from uncertsplat.schemas.metrics import EvalReport, ViewMetrics
from uncertsplat.schemas.prune import PruneMetrics, PruneReport, PruneSweep, SweepPoint
from uncertsplat.schemas.reconstruct import ReconstructReport
from uncertsplat.schemas.runs import (
    Manifest,
    PosteriorSummary,
    RunExposure,
    SweepRecord,
    SweepSummary,
    TrainSummary,
)
from uncertsplat.schemas.scene import RunScene, SynthScene, ViewsAdded
from uncertsplat.schemas.select import Selection

__all__ = ["EvalReport", "Manifest", "PosteriorSummary", "PruneMetrics", "PruneReport", "PruneSweep",
           "ReconstructReport", "RunExposure", "RunScene", "SchemaFile", "Selection", "Strict", "SweepPoint", "SweepRecord", "SweepSummary",
           "SynthScene", "TrainSummary", "ViewMetrics", "ViewsAdded"]
