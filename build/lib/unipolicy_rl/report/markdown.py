"""report.md: sections of prose, tables and embedded figures, written in one go.

Figures are linked by paths relative to report.md, so the report folder can be moved,
zipped or committed whole and still renders (GitHub, VS Code, any markdown viewer).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path


@dataclass
class Section:
    title: str
    blocks: list[str] = field(default_factory=list)  # markdown paragraphs, tables, images, in order


def table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    def line(cells: Sequence[str]) -> str:
        return "| " + " | ".join(str(cell).replace("|", "\\|") for cell in cells) + " |"

    return "\n".join([line(header), "|" + "---|" * len(header), *(line(row) for row in rows)])


def image(path: Path, report_dir: Path, caption: str) -> str:
    return f"![{caption}]({path.relative_to(report_dir).as_posix()})"


def bullets(items: Sequence[str]) -> str:
    return "\n".join(f"- {item}" for item in items)


def write_markdown(path: Path, title: str, intro: Sequence[str], sections: Sequence[Section]) -> Path:
    parts = [f"# {title}", *intro]
    for section in sections:
        parts.append(f"## {section.title}")
        parts.extend(section.blocks)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n\n".join(parts) + "\n")
    return path
