"""``python -m uncertsplat``: the same command line as the ``uncertsplat`` script.

Useful where the package is importable but its script is not on ``PATH`` (a ``--target`` install, a source
checkout on ``PYTHONPATH``).
"""

from uncertsplat.cli import app

if __name__ == "__main__":
    app(prog_name="uncertsplat")
