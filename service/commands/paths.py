"""Checks of the commands' output paths, made before their work (a traceback came after it)."""
from __future__ import annotations

import os
from pathlib import Path


def output_file_problem(path) -> str:
    """Why ``path`` cannot be written as an output file ("" when it can): its folder is made
    if missing, and must be writable; ``path`` must not be a folder."""
    path = Path(path)
    if path.is_dir():
        return "is a folder"
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        return f"its folder cannot be made ({e.strerror or e})"
    return "" if os.access(path.parent, os.W_OK) else "its folder is not writable"


def output_folder_problem(path) -> str:
    """Why ``path`` cannot be the folder of a command's outputs ("" when it can): it is made if
    missing; a file there, or a folder that cannot be made, is said in parentheses."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        return "(a file is there)"
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        return f"({e.strerror or e})"
    return ""
