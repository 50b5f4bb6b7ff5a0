"""Where installed data files are read: through `importlib.resources`, never by a path relative to the source
tree, so a wheel installed anywhere (`pip install .`, pipx) finds them as an editable checkout does.

The card's presets, rig files and EDS are the data of the `configs` package (the top-level `configs/` folder);
the service's page is `api`'s, the catalog's migrations `rig.store`'s. A leaf module: it imports nothing of
ours, so every package may use it (`drivers` as it uses `model.errors`).
"""

from __future__ import annotations

import importlib.resources
from pathlib import Path


def package_folder(package: str, *parts: str) -> Path:
    """A data folder inside an installed package, as a directory path.

    A path, not a Traversable: callers glob the folders and hand files to libraries that open them by name
    (canopen's EDS import, alembic's script directory, Starlette's static files). A wheel always installs
    as files, so an installed package's folder is a real directory.
    """
    root = importlib.resources.files(package)
    if not isinstance(root, Path):
        raise RuntimeError(
            f"{package}: installed as {root!r}, not as files; reinstall hdrig with pip or pipx"
        )
    return root.joinpath(*parts)


def card_folder(name: str) -> Path:
    """The card's `configs/<name>` folder (`models`, `rigs` or `eds`), wherever hdrig is installed."""
    return package_folder("configs", name)
