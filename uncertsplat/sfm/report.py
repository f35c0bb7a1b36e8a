"""The health report of ``uncertsplat reconstruct``: ``WORKSPACE/reconstruct_report.json``.

The report is written for successful and failed runs alike (``success`` says which), so a user, and
the later stages, can see why a reconstruction is not trustworthy: which images did not register, how
many disconnected models COLMAP found, and how well the cameras fit the points.
"""

from __future__ import annotations

from pathlib import Path

from uncertsplat.console import q
from uncertsplat.errors import UserError
from uncertsplat.schemas.reconstruct import (
    EXTEND_DIR,
    FAILED_REPORT_NAME,
    OVERWRITE_MOVING,
    OVERWRITE_OLD,
    OVERWRITE_RESTORING,
    REPORT_NAME,
    REPORT_SCHEMA_VERSION,
    CameraSummary,
    MappingAttempt,
    ModelSummary,
    ReconstructReport,
)


def report_path(workspace: str | Path) -> Path:
    return Path(workspace) / REPORT_NAME


def write_report(workspace: str | Path, report: ReconstructReport) -> Path:
    """Write the report atomically to ``WORKSPACE/reconstruct_report.json``."""
    return report.write(report_path(workspace))


def load_report(workspace: str | Path) -> ReconstructReport | None:
    """The report of a workspace, or None when there is none (e.g. a workspace made by COLMAP itself).

    Raises:
        UserError: when the file exists but is not a valid report.
    """
    return ReconstructReport.read_optional(report_path(workspace))


UNFINISHED = "unfinished: the run stopped before it ended"
"""The message of a report written as a reconstruction starts (``stages.reconstruct``): what is left when it was
stopped (Ctrl-C, a crash) before it could write its outcome."""


def require_successful(workspace: str | Path) -> ReconstructReport | None:
    """Refuse a workspace whose reconstruct report says it failed (used by ``train``).

    Returns the report, or None for a workspace without one (made by another tool: accepted).
    """
    report = load_report(workspace)
    if report is not None and not report.success and report.message == UNFINISHED:
        from uncertsplat.io.atomic import lock_holder

        holder = lock_holder(workspace)
        if holder is not None:
            raise UserError(f"a reconstruction is writing this workspace now ({holder})", path=workspace,
                            hint="Wait for it to finish, then run this again.")
        if any((Path(workspace) / n).is_dir() for n in (OVERWRITE_MOVING, OVERWRITE_OLD, OVERWRITE_RESTORING)):
            # (killed: the workspace it was replacing waits in the folder, put back by the next reconstruct of it)
            raise UserError("this workspace's reconstruct --overwrite was stopped before it finished",
                            path=report_path(workspace),
                            hint=f"Any `uncertsplat reconstruct {q(report.photos)} -o {q(workspace)}` puts back the "
                                 "workspace it was replacing before anything else (with --overwrite and its options "
                                 "it then starts the replacement over).")
        raise UserError("this workspace comes from a reconstruction that was stopped before it finished",
                        path=report_path(workspace),
                        hint=f"Run the same `uncertsplat reconstruct` command (photos {report.photos}, output "
                             f"{workspace}, and its options) again: it starts over in this folder.")
    if report is not None and not report.success:
        missing = len(report.images_unregistered)
        raise UserError(
            f"this workspace comes from a failed reconstruction ({report.message or 'see the report'}; "
            f"{missing} image(s) unregistered)",
            path=report_path(workspace),
            hint="Fix the photos (more overlap, sharper images) and run `uncertsplat reconstruct` again.",
        )
    return report


__all__ = ["EXTEND_DIR", "FAILED_REPORT_NAME", "OVERWRITE_MOVING", "OVERWRITE_OLD", "OVERWRITE_RESTORING", "REPORT_NAME", "REPORT_SCHEMA_VERSION", "UNFINISHED", "CameraSummary", "MappingAttempt", "ModelSummary", "ReconstructReport",
           "load_report", "report_path", "require_successful", "write_report"]
