"""How a benchmark script hands over its table: printed, and written as Markdown."""
from __future__ import annotations

from pathlib import Path


def write_report(path: Path, text: str) -> None:
    """Print ``text`` and write it to ``path`` (its folder made if missing), ending in one
    newline: the file `make bench` leaves in bench-output/."""
    print(text)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text.rstrip("\n") + "\n", encoding="utf-8")
