"""Where installed data files are read: through `importlib.resources`, never by a path relative to the source
tree, so a wheel installed anywhere (`pip install .`, pipx) finds them as an editable checkout does.

The card's presets, rig files and EDS are the data of the `configs` package (the top-level `configs/` folder);
the service's page is `api`'s, the catalog's migrations `rig.store`'s. A leaf module: it imports nothing of
ours, so every package may use it (`drivers` as it uses `model.errors`).
"""

from __future__ import annotations

import importlib.resources
from importlib.resources.abc import Traversable
from pathlib import Path


def package_folder(package: str, *parts: str) -> Path:
    """A data folder inside an installed package, as a directory path.

    A path, not a Traversable: callers glob the folders and hand files to libraries that open them by name
    (canopen's EDS import, alembic's script directory, Starlette's static files). A wheel always installs
    as files, so an installed package's folder is a real directory.
    """
    root = importlib.resources.files(package)
    return _as_path(root, package).joinpath(*parts)


def card_folder(name: str) -> Path:
    """The card's `configs/<name>` folder (`models`, `rigs` or `eds`), wherever hdrig is installed."""
    try:
        root: Traversable = importlib.resources.files("configs")
    except ModuleNotFoundError:
        # An editable install made before configs/ became a package maps only the packages it knew then;
        # until it is renewed (`make install`), the checkout's folder beside this package stands in.
        root = Path(__file__).resolve().parent.parent / "configs"
        if not root.is_dir():
            raise
    return _as_path(root, "configs") / name


def _as_path(root: Traversable, package: str) -> Path:
    if not isinstance(root, Path):
        raise RuntimeError(
            f"{package}: installed as {root!r}, not as files; reinstall hdrig with pip or pipx"
        )
    return root
