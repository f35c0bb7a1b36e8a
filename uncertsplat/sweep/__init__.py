"""Speed-accuracy sweeps: spec -> independent jobs -> one record per point -> Pareto fronts.

``spec`` (what varies), ``jobs`` (``run_job(job_dict) -> records``, runnable anywhere), ``pareto``
(``pareto_front``, the sweep's ``summarize`` and its figure). The stage ``stages.sweep.run`` ties them
together on local cores.
"""

from uncertsplat.sweep.pareto import pareto_front, plot_pareto

__all__ = ["pareto_front", "plot_pareto"]
