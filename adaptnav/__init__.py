"""adaptnav: model-aided inertial navigation for AUVs with an online-learned motion model.

The repository keeps one top-level folder per layer (``fusion/``, ``calibration/``,
``sonar/``, ``sim/``, ``service/``); installed, they are the subpackages
``adaptnav.fusion``, ``adaptnav.calibration``, ``adaptnav.sonar``, ``adaptnav.sim`` and
``adaptnav.service`` (``pyproject.toml`` maps the folders), so nothing collides with
another distribution's top-level ``service`` or ``sim``.
"""

from importlib.metadata import PackageNotFoundError, version as _version

try:
    __version__ = _version("adaptnav")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0+unknown"
