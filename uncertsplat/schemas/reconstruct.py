"""Schema of ``WORKSPACE/reconstruct_report.json``, the health report of ``uncertsplat reconstruct``.

The report is written for successful and failed runs alike (``success`` says which), so a user, and
the later stages, can see why a reconstruction is not trustworthy: which images did not register, how
many disconnected models COLMAP found, and how well the cameras fit the points.
"""

from __future__ import annotations

from typing import Any

from pydantic import ConfigDict, Field

from uncertsplat.schemas.base import SchemaFile, Strict

REPORT_NAME = "reconstruct_report.json"
EXTEND_DIR = ".extend_tmp"
"""Where ``reconstruct --extend`` builds the grown workspace inside it; ``EXTEND_DIR/old`` holds the parts it
replaced while it swaps them (``stages.reconstruct.extend``; ``sfm.scene.load_scene`` refuses a half-made swap)."""
OVERWRITE_OLD = ".overwrite_old"
"""Where ``reconstruct --overwrite`` keeps the finished workspace it replaces until the new one has finished: put back
after a failure, a stop or a kill (``stages.reconstruct``), so a failed --overwrite never loses a workspace."""
OVERWRITE_MOVING = ".overwrite_moving"
"""Where --overwrite moves a finished workspace's files one by one; renamed ``OVERWRITE_OLD`` once all are there."""
OVERWRITE_RESTORING = ".overwrite_restoring"
"""``OVERWRITE_OLD`` once the new run's files are gone, while its files go back."""
FAILED_REPORT_NAME = ".reconstruct_report.failed.json"
"""The report of an --overwrite that failed, kept beside the workspace it was to replace (put back); hidden, so that
the workspace, put back as it was, is the same input to the stages that read it (their fingerprints skip hidden
files)."""
REPORT_SCHEMA_VERSION = 3


class _Base(Strict):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, validate_assignment=True)


class CameraSummary(_Base):
    """One estimated (distorted) camera of the kept model."""

    camera_id: int
    model: str
    width: int
    height: int
    params: list[float]
    num_images: int


class ModelSummary(_Base):
    """One model returned by incremental mapping (COLMAP may split a capture into several)."""

    index: int
    num_images: int
    num_points3d: int
    image_names: list[str]
    kept: bool


class MappingAttempt(_Base):
    """One run of incremental mapping (``reconstruct`` maps again with another seed until two runs agree)."""

    seed: int
    relaxed: bool
    num_images: int
    """Images registered in the run's largest model."""
    num_points3d: int
    num_observations: int
    """Feature observations the largest model explains (the sum of its points' track lengths): what the kept run
    maximises."""
    mean_reprojection_error: float | None = None
    focal_lengths: dict[str, float] = {}
    """Camera id -> estimated focal length (pixels of the distorted images)."""
    seconds: float = 0.0
    """Time of this mapping run."""
    kept: bool = False


class ReconstructReport(SchemaFile):
    """What ``reconstruct`` did and how healthy the result is (``WORKSPACE/reconstruct_report.json``)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, validate_assignment=True)
    FILE_NAME = REPORT_NAME
    SCHEMA_VERSION = REPORT_SCHEMA_VERSION
    WRITTEN_BY = "uncertsplat reconstruct"

    schema_version: int = REPORT_SCHEMA_VERSION
    success: bool
    """False when the run stopped (too few images registered, no overlap); ``train`` refuses it."""
    message: str = ""
    """Why the run failed, or notes for a successful run."""
    photos: str
    """The input folder, as given (resolved to an absolute path)."""
    inputs_fingerprint: str = ""
    """Hash of the input file names, sizes and modification times (detects a changed photo folder)."""
    photo_sha256: dict[str, str] = {}
    """Image name -> SHA-256 of the photo file, of every photo found (``--extend`` names a photo edited since);
    empty in reports before version 3."""
    images_found: list[str] = []
    images_registered: list[str] = []
    images_unregistered: list[str] = []
    registered_fraction: float = Field(0.0, ge=0.0, le=1.0)
    ignored: list[str] = []
    """Entries of the photo folder that were not used (sub-folders, non-image files)."""
    rotated: list[str] = []
    """Images whose EXIF orientation was applied (staged as rotated copies)."""
    notes: list[str] = []
    image_sizes: dict[str, int] = {}
    """'WxH' -> number of images of that size (one camera per size in single-camera mode)."""
    matcher: str = ""
    """The matcher actually used (auto resolved)."""
    num_verified_pairs: int = 0
    models_found: int = 0
    models: list[ModelSummary] = []
    retried_relaxed: bool = False
    """Whether mapping was repeated with relaxed options because too few images registered."""
    mapping_attempts: list[MappingAttempt] = []
    """Every mapping run, in order (``kept``: the one the workspace holds)."""
    mapping_agreed: bool | None = None
    """Whether two mapping runs found the same geometry (``sfm.reconstruct.attempts_agree``); None with one run
    (``--mapping-attempts 1``). False: the kept run is the best of runs that disagreed; check the poses."""
    num_points3d: int = 0
    mean_reprojection_error: float | None = None
    """Pixels, in the kept model before undistortion."""
    mean_track_length: float | None = None
    mean_observations_per_image: float | None = None
    num_observations: int | None = None
    """Feature observations of the kept model (the sum of its points' track lengths)."""
    cameras: list[CameraSummary] = []
    undistorted_size: dict[str, list[int]] = {}
    """Image name -> [width, height] after undistortion, for the images in ``WORKSPACE/images``."""
    ground_truth: dict[str, float] | None = None
    """When the photos are a synthetic scene's ``images/``: the cameras' error against its GT cameras
    (``sfm.reconstruct.pose_accuracy``: centre error in % of the rig radius, rotation and focal errors)."""
    stage_seconds: dict[str, float] = {}
    total_seconds: float = 0.0
    pycolmap_version: str = ""
    colmap_version: str = ""
    options: dict[str, Any] = {}
    """The ReconstructConfig used (model_dump)."""

    @classmethod
    def _upgrade(cls, data: dict, version: int) -> dict | None:
        # version 1 mapped once: no list of runs, no agreement test, no observation count (files written between
        # those keys' arrival and the version's bump have them: kept)
        if version == 1:
            data = {"mapping_attempts": [], "mapping_agreed": None, "num_observations": None, **data}
        elif version != 2:
            return None
        return {"photo_sha256": {}, **data}  # (version 2 had no per-photo hashes)

    def summary(self) -> str:
        """One line for the console."""
        n, r = len(self.images_found), len(self.images_registered)
        err = "n/a" if self.mean_reprojection_error is None else f"{self.mean_reprojection_error:.2f} px"
        # (several models: the workspace holds the largest; "2 model(s)" beside 12/12 read as a split capture)
        models = "" if self.models_found <= 1 else f" in the largest of {self.models_found} models"
        return (f"{r}/{n} images registered{models}, {self.num_points3d} points, "
                f"reprojection error {err}, {self.total_seconds:.1f} s")
