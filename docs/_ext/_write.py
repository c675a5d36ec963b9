"""Shared helper of the docs generators: write a file only when its content changes."""
from pathlib import Path


def write_if_changed(path, text):
    """Write ``text`` to ``path`` (creating folders) unless it already holds exactly that."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.is_file() and path.read_text(encoding="utf-8") == text:
        return False
    path.write_text(text, encoding="utf-8")
    return True
