"""MkDocs hook: the configuration reference, generated from conf/**/*.yaml and their comments.

Every knob (a leaf key of a config file) is documented by the comment on its line or by the
comment block directly above it; a file's first comment block describes the option itself. A knob
without a comment is logged as a warning, which fails ``mkdocs build --strict``. ``_target_`` (the
class a node builds), the ``defaults`` list and the ``hydra`` section are Hydra's own and listed
without a comment of ours.

The page that holds the marker ``<!-- config-reference -->`` receives the generated reference.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

MARKER = "<!-- config-reference -->"
# mkdocs counts warnings of loggers under "mkdocs" toward --strict.
log = logging.getLogger("mkdocs.hooks.config_reference")

_KEY = re.compile(r"^(?P<indent> *)(?P<key>[A-Za-z_][\w@.\-]*):(?P<rest>.*)$")
_HYDRA_OWN = {"_target_", "defaults", "hydra"}


@dataclass
class Knob:
    path: str  # dotted key within the file
    value: str  # the raw default, as written
    comment: str  # its documentation ("" when missing)
    line: int


@dataclass
class ConfigFile:
    group: str  # "" for conf/config.yaml
    option: str  # the file's stem: what `group=option` selects
    description: str
    knobs: list[Knob] = field(default_factory=list)
    target: str | None = None  # the class the file's root node builds

    @property
    def missing(self) -> list[Knob]:
        return [
            k for k in self.knobs if not k.comment and not ({k.path.split(".")[0], k.path.split(".")[-1]} & _HYDRA_OWN)
        ]


def _split_comment(text: str) -> tuple[str, str]:
    """``value  # comment`` -> (value, comment); a ``#`` inside quotes or ${...} is kept."""
    depth, quote = 0, None
    for i, ch in enumerate(text):
        if quote:
            quote = None if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch in "{[":
            depth += 1
        elif ch in "}]":
            depth -= 1
        elif ch == "#" and depth == 0 and (i == 0 or text[i - 1] in " \t"):
            return text[:i].strip(), text[i + 1 :].strip()
    return text.strip(), ""


def parse(path: Path, conf_dir: Path) -> ConfigFile:
    relative = path.relative_to(conf_dir)
    group = "/".join(relative.parts[:-1])
    lines = path.read_text().splitlines()
    description: list[str] = []
    block: list[str] = []  # the comment block just read
    seen_key = False
    stack: list[tuple[int, str]] = []  # (indent, key) of the open mapping nodes
    knobs: list[Knob] = []
    target = None
    last: Knob | None = None  # the knob whose line comment may continue on the next lines
    last_indent = -1
    for number, raw in enumerate(lines, start=1):
        stripped = raw.strip()
        if not stripped:
            if not seen_key and block:
                description, block = block, []
            block, last = [], None
            continue
        indent = len(raw) - len(raw.lstrip(" "))
        if stripped.startswith("#"):
            text = stripped.lstrip("#").strip()
            if text.startswith("@package"):
                continue
            if last is not None and indent > last_indent:
                last.comment = f"{last.comment} {text}".strip()  # the line comment continues
            else:
                last = None
                block.append(text)
            continue
        if stripped.startswith("- "):
            continue  # an item of a block list (the defaults list)
        match = _KEY.match(raw)
        if match is None:
            continue
        if not seen_key and block:
            # The file's first comment block describes the option; a knob right below it without a
            # comment of its own is documented by it too.
            description = block
            if match["key"] in _HYDRA_OWN:
                block = []
        seen_key = True
        while stack and stack[-1][0] >= indent:
            stack.pop()
        value, comment = _split_comment(match["rest"])
        key = match["key"]
        dotted = ".".join([k for _, k in stack] + [key])
        documented = comment or " ".join(block)
        block = []
        if value == "":  # a mapping (or a block list) follows
            stack.append((indent, key))
            last = None
            continue
        if key == "_target_":
            if not stack:
                target = value
            else:
                knobs.append(Knob(dotted, value, documented or "the class this node builds", number))
            last = None
            continue
        knob = Knob(dotted, value, documented, number)
        knobs.append(knob)
        last, last_indent = (knob, indent) if comment else (None, -1)
    return ConfigFile(group, path.stem, " ".join(description), knobs, target)


def read_all(conf_dir: Path) -> list[ConfigFile]:
    files = sorted(conf_dir.rglob("*.yaml"), key=lambda p: (len(p.relative_to(conf_dir).parts), str(p)))
    return [parse(path, conf_dir) for path in files]


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def render(files: list[ConfigFile]) -> str:
    out: list[str] = []
    groups: dict[str, list[ConfigFile]] = {}
    for config in files:
        groups.setdefault(config.group, []).append(config)
    for group, configs in groups.items():
        if group == "":
            out.append("## The top-level config (`conf/config.yaml`)\n")
        else:
            options = ", ".join(f"`{c.option}`" for c in configs)
            out.append(f"## `{group}`\n")
            out.append(f"`conf/{group}/`; options: {options}.\n")
        for config in configs:
            where = f"conf/{group + '/' if group else ''}{config.option}.yaml"
            if group:
                out.append(f"### `{group}={config.option}`\n")
            if config.description:
                out.append(_cell(config.description) + "\n")
            if config.target:
                out.append(f"Builds `{config.target}` (`{where}`).\n")
            else:
                out.append(f"`{where}`\n")
            if config.knobs:
                out.append("| knob | default | what it sets |")
                out.append("|---|---|---|")
                for knob in config.knobs:
                    out.append(f"| `{knob.path}` | `{_cell(knob.value)}` | {_cell(knob.comment)} |")
                out.append("")
    return "\n".join(out)


def _conf_dir(config) -> Path:
    return Path(config["config_file_path"]).parent / "conf"


def on_page_markdown(markdown, page, config, files):
    if MARKER not in markdown:
        return markdown
    configs = read_all(_conf_dir(config))
    for config_file in configs:
        for knob in config_file.missing:
            where = f"conf/{config_file.group + '/' if config_file.group else ''}{config_file.option}.yaml"
            log.warning("%s:%d: the knob %s has no comment", where, knob.line, knob.path)
    return markdown.replace(MARKER, render(configs))
