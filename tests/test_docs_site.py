"""The documentation site builds strictly, has every page of its nav, and every image it shows exists."""

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
HOOKS = ROOT / "docs" / "hooks"


def _nav_pages(nav) -> list[str]:
    pages = []
    for item in nav:
        value = next(iter(item.values())) if isinstance(item, dict) else item
        pages.extend(_nav_pages(value) if isinstance(value, list) else [value])
    return pages


def _load_hook():
    spec = importlib.util.spec_from_file_location("config_reference", HOOKS / "config_reference.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def test_every_config_knob_has_a_comment():
    hook = _load_hook()
    configs = hook.read_all(ROOT / "conf")
    missing = [f"conf/{c.group}/{c.option}.yaml: {k.path}" for c in configs for k in c.missing]
    assert missing == []
    assert len({(c.group, c.option) for c in configs}) == len(list((ROOT / "conf").rglob("*.yaml")))
    assert all(c.description for c in configs if c.group), "every option describes itself"


def test_a_knob_without_a_comment_is_reported(tmp_path):
    hook = _load_hook()
    (tmp_path / "algo").mkdir()
    (tmp_path / "algo" / "toy.yaml").write_text(
        "# A toy learner.\n_target_: toy.Learner\nrate: 0.1   # its step size\nsteps: 3\n"
        "# a block above documents the next knob\nwidth: 4\nnested:\n  depth: 2\n"
    )
    (config,) = hook.read_all(tmp_path)
    assert config.description == "A toy learner." and config.target == "toy.Learner"
    assert [k.path for k in config.knobs] == ["rate", "steps", "width", "nested.depth"]
    assert [k.path for k in config.missing] == ["steps", "nested.depth"]
    assert "| `rate` | `0.1` | its step size |" in hook.render([config])


@pytest.mark.skipif(importlib.util.find_spec("mkdocs") is None, reason="the docs extra is not installed")
def test_the_site_builds_with_every_page_and_image(tmp_path):
    site = tmp_path / "site"
    built = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
    )
    assert built.returncode == 0, built.stdout + built.stderr
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text())
    pages = _nav_pages(config["nav"])
    assert "configuration.md" in pages and "api.md" in pages
    for page in pages:
        html = site / (page[: -len(".md")] + "/index.html" if page != "index.md" else "index.html")
        assert html.is_file(), f"{page} was not built"
        text = html.read_text()
        for source in re.findall(r'<img[^>]+src="([^"]+)"', text):
            if source.startswith(("http://", "https://", "data:")):
                continue
            assert (html.parent / source).resolve().is_file(), f"{page} shows {source}, which does not exist"
    # every image a page's markdown references exists in the repository
    for markdown in (ROOT / "docs").rglob("*.md"):
        for target in re.findall(r"!\[[^\]]*\]\(([^)\s]+)", markdown.read_text()):
            assert (markdown.parent / target).resolve().is_file(), f"{markdown.name} shows {target}"
    # the configuration reference was generated, the tutorials include their examples
    assert "max_kl" in (site / "configuration/index.html").read_text()
    assert "one_robot" in (site / "tutorials/env_alone/index.html").read_text()


def test_the_readme_is_short_and_starts_with_its_two_commands():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 150
    block = lines[lines.index("```bash") + 1 :][:2]
    assert block == [
        "pip install torch==2.13.0 -e . && python train.py",
        'pip install torch==2.13.0 -e ".[test]" && pytest -q',
    ]
    for target in re.findall(r"\]\(((?:docs|examples)/[^)#\s]+)", "\n".join(lines)):
        assert (ROOT / target).is_file(), f"the README links {target}, which does not exist"
