"""``python -m uncertsplat``: the same command line as the ``uncertsplat`` script.

Useful where the package is importable but its script is not on ``PATH`` (a ``--target`` install, a source
checkout on ``PYTHONPATH``).
"""

from uncertsplat.cli import _STATE, app

if __name__ == "__main__":
    _STATE["process"] = True  # (as the console script's entrypoint: see cli._ignore_further_interrupts)
    app(prog_name="uncertsplat")
