"""What a file a command was given is, when it is not the kind the command reads: a record uncertsplat writes (one of
``schemas``), a pipeline, a sweep spec or one command's configuration, told by its keys (``what_file_is``). A
``--config`` file, ``run`` or ``sweep`` given such a file said so in one clause per key, or with a TOML parser's
"Invalid statement"; here, above both the settings (``config``) and the records, it is named in one sentence."""

from __future__ import annotations

import uncertsplat.schemas as schemas
from uncertsplat.config import SWEEP_KEYS, config_owner

RECORDS_WRITTEN = (
    ("SynthScene", "`uncertsplat synth`'s record of a synthetic scene (scene.json)"),
    ("Manifest", "a pipeline stage's record (manifest.json, written by `uncertsplat run`)"),
    ("TrainSummary", "`uncertsplat train`'s summary of a training (train_summary.json)"),
    ("PruneReport", "`uncertsplat prune`'s report (prune.json)"),
    ("PruneSweep", "`uncertsplat prune --sweep`'s record (sweep.json)"),
    ("SweepSummary", "`uncertsplat sweep`'s summary (sweep.json)"),
    ("Selection", "`uncertsplat select-views`' record (selection.json)"),
    ("ReconstructReport", "`uncertsplat reconstruct`'s report (reconstruct_report.json)"),
    ("RunExposure", "`uncertsplat train`'s exposure record (exposure.json)"),
    ("RunScene", "`uncertsplat train`'s record of the run's scene (scene.json)"),
)
"""The records uncertsplat writes that ``what_file_is`` tells by their required keys, the most specific first (a
run's scene.json has few)."""


METRICS_WORDS = "`uncertsplat evaluate`'s metrics (metrics.json)"


def own_words(model: type) -> str | None:
    """How ``what_file_is`` names a file of the schema ``model`` (None: a schema it does not tell)."""
    if model is schemas.EvalReport:
        return METRICS_WORDS
    return next((words for name, words in RECORDS_WRITTEN if getattr(schemas, name) is model), None)


def identifying_keys(model: type) -> set[str]:
    """The keys ``what_file_is`` tells a file of the schema ``model`` by: its required keys (``EvalReport``, which
    requires none, by its per-view metrics and their mean)."""
    if model is schemas.EvalReport:
        return {"per_view", "mean"}
    return {k for k, f in model.model_fields.items() if f.is_required()}


def what_file_is(data: dict) -> str | None:
    """What a file that is not the one a command expects is, from its keys: a record uncertsplat writes (e.g.
    "`uncertsplat train`'s summary of a training (train_summary.json)"), a pipeline, a sweep spec or a command's
    configuration; None when it is none of them (a mistyped file: the command's reader names the key)."""
    if not isinstance(data, dict) or not data:
        return None
    if "schema_version" in data:
        if identifying_keys(schemas.EvalReport) <= set(data):
            return METRICS_WORDS
        for name, words in RECORDS_WRITTEN:
            if identifying_keys(getattr(schemas, name)) <= set(data):
                return words
        return "a record uncertsplat writes (it has a schema_version)"
    if isinstance(data.get("stages"), list):
        return "a pipeline (it lists [[stages]])"
    if len(SWEEP_KEYS & set(data)) >= 2:  # (one could be a misspelt setting)
        return "a sweep spec"
    owner = config_owner(data)
    return f"`uncertsplat {owner}`'s configuration" if owner else None


__all__ = ["METRICS_WORDS", "RECORDS_WRITTEN", "identifying_keys", "own_words", "what_file_is"]
