"""Folders that live at the repository root but ship inside the package (found for the whole
package, hence the root).

`migrations/` and `web/` stay where developers expect them; a wheel installs them as the
packages `service.migrations` and `service.web` (see setup.py). Either way the program
finds them through here.
"""

from __future__ import annotations

import importlib.util
from collections.abc import Callable
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]


def shipped_dir(package: str, repo_folder: str, is_ours: Callable[[Path], bool]) -> Path:
    """The installed package's folder, else the source tree's; `is_ours` rejects a stranger of the
    same name."""
    spec = importlib.util.find_spec(package)
    for location in (spec.submodule_search_locations or []) if spec else []:
        if is_ours(Path(location)):
            return Path(location)
    source_tree = REPO_ROOT / repo_folder
    if is_ours(source_tree):
        return source_tree
    raise RuntimeError(f"{repo_folder}/ is missing from this tiltlab installation")
