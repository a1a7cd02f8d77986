"""condtrack: batch point tracking with conditional filters (``import condtrack_cli as ct; ct.track(...)``).

Implements the conditional linear (CLF) and nonlinear (CNLF) filters of Arnaud,
Mémin & Cernuschi-Frías, "Filtrage conditionnel pour la trajectographie dans des
séquences d'images", RFIA 2004, with the baselines STK and MDR.
"""

from condtrack_cli.errors import CondtrackError, CondtrackWarning

__version__ = "0.1.0"

#: Largest seed (``--seed``, ``ct.track(seed=...)``): the HDF5 file stores it as a signed 64-bit integer.
MAX_SEED = 2**63 - 1

#: Version of the output schema (CSV columns, HDF5 layout); see docs/schema.md.
SCHEMA_VERSION = "2.0"

#: Schema versions the readers accept: 1.0 files have no ``dof`` (read as Gaussian, dof inf) and no
#: ``/tracks/trackability`` (read as NaN, unknown).
READABLE_SCHEMA_VERSIONS = ("1.0", "2.0")

#: The pixel convention stated in every output file.
COORDINATES = (
    "pixels; x to the right, y down; origin (0,0) at the centre of the top-left pixel "
    "(OpenCV convention)"
)

#: The Python API (``condtrack_cli.api``), imported on first use so that ``import condtrack_cli`` stays light.
_API = ("track", "read_tracks", "Tracks")

#: The public names, the lazy ones included: ``from condtrack_cli import *``, ``dir(ct)`` and a notebook's completion.
__all__ = ["track", "read_tracks", "Tracks", "CondtrackError", "CondtrackWarning", "MAX_SEED", "SCHEMA_VERSION",
           "READABLE_SCHEMA_VERSIONS", "COORDINATES"]


def __getattr__(name: str):
    if name in _API:
        from condtrack_cli import api

        return getattr(api, name)
    raise AttributeError(f"module 'condtrack_cli' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_API))
