"""The package's version and folder, importable however ``sgvloc`` itself resolves.

A folder named ``sgvloc`` in the working directory (a checkout of this repository, say)
can stand in for the package's ``__init__`` under an editable install: ``sgvloc`` is then
a namespace whose submodules still load. Package data is therefore found next to this
module, never through ``sgvloc`` or ``importlib.resources.files("sgvloc")``.
"""

from pathlib import Path

__version__ = "0.1.0"
#: the installed package's folder (weights/, calibration/)
PACKAGE_DIR = Path(__file__).resolve().parent
