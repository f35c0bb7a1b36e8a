"""Schema of ``OUT/selection.json`` (``uncertsplat select-views``)."""

from __future__ import annotations

from pydantic import Field

from uncertsplat.schemas.base import SchemaFile, Strict


class CandidateScore(Strict):
    """One candidate camera and its score."""

    name: str
    score: float | None
    """The policy's score before any choice; higher = taken first. None where the candidate got no score: outside the
    capture's gaps (``fisher``'s ``gaps``), a pose no camera can stand at as far as the photos tell (the notes say
    which), or a NaN; a chosen view's ``score_when_chosen`` is its score at its turn."""
    cam_from_world: list[list[float]]
    """[4,4] in the run's normalised world (``RUN/scene.json`` has the similarity to the scene's own)."""
    position: list[float]
    """Camera centre, run world."""
    pose_line: str | None = None
    """The same pose as a line of a ``--candidates`` file, ``NAME QW QX QY QZ TX TY TZ`` in the scene's own (COLMAP)
    frame: what a plan file or a capture tool reads."""
    depth_std: float | None = None
    """variance: the mean depth std of the candidate's render (scene units)."""


class ChosenView(CandidateScore):
    rank: int
    """1 = the first choice."""
    score_when_chosen: float | None
    """The score at the greedy step that chose it (fisher and coverage change after each choice)."""


class Selection(SchemaFile):
    """``OUT/selection.json``: the views ``select-views`` chose and how."""

    FILE_NAME = "selection.json"
    SCHEMA_VERSION = 2
    WRITTEN_BY = "uncertsplat select-views"

    schema_version: int = 2
    run: str
    score: str
    candidates: str
    """The ``--candidates`` value."""
    num_candidates: int
    chosen: list[ChosenView]
    ranking: list[CandidateScore] = Field(default_factory=list)
    """Every candidate, by descending score (before any choice)."""
    used: list[str] = Field(default_factory=list)
    """The views the run had trained on."""
    seconds: float
    """Time spent scoring and choosing (not loading)."""
    seconds_per_candidate: float
    settings: dict = Field(default_factory=dict)
    """K, resolution, probes, seed, noise (what the score was computed with)."""

    @classmethod
    def _upgrade(cls, data: dict, version: int) -> dict | None:
        # version 1 had no pose_line (read as not recorded)
        return {**data, "schema_version": cls.SCHEMA_VERSION} if version == 1 else None
