"""The README stays short and every link in the README and docs/*.md resolves (files and #anchors; no network)."""
from __future__ import annotations

import re
import tomllib
from pathlib import Path
from urllib.parse import unquote, urlparse

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
PAGES = [README, *sorted((ROOT / "docs").glob("*.md"))]

_FENCE = re.compile(r"^ {0,3}(```|~~~).*?^ {0,3}\1[^\n]*$", re.M | re.S)
_CODE_SPAN = re.compile(r"(`+)(.+?)\1", re.S)
_INLINE_LINK = re.compile(r"!?\[((?:[^\[\]]|\[[^\[\]]*\])*)\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
_REF_DEF = re.compile(r"^ {0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s+\"[^\"]*\")?\s*$", re.M)
_HEADING = re.compile(r"^ {0,3}(#{1,6})\s+(.*?)\s*#*\s*$", re.M)


def _prose(text: str) -> str:
    """The markdown without fenced code blocks, code spans kept as plain text (links inside code are not links)."""
    text = _FENCE.sub("", text)
    return _CODE_SPAN.sub(lambda m: m.group(2).replace("[", " ").replace("]", " ").replace("(", " "), text)


def github_slug(heading: str) -> str:
    """The anchor GitHub gives a heading: rendered text, lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link renders as its text
    text = text.strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every heading anchor of a markdown file, numbered -1, -2, ... for repeated headings as GitHub does."""
    seen: dict[str, int] = {}
    out: set[str] = set()
    for m in _HEADING.finditer(_FENCE.sub("", path.read_text(encoding="utf-8"))):
        slug = github_slug(m.group(2))
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        out.add(slug if n == 0 else f"{slug}-{n}")
    return out


def links(path: Path) -> list[str]:
    """The targets of every inline link, image and reference definition in a markdown file, outside code."""
    text = _prose(path.read_text(encoding="utf-8"))
    return [m.group(2) for m in _INLINE_LINK.finditer(text)] + _REF_DEF.findall(text)


def test_slug_rule_matches_github() -> None:
    assert github_slug("Two commands") == "two-commands"
    assert github_slug("The shipped model (`assets/perception/model/`, 18 MB of safetensors)") == \
        "the-shipped-model-assetsperceptionmodel-18-mb-of-safetensors"
    assert github_slug("Closed loop: judging perception by grasp success") == \
        "closed-loop-judging-perception-by-grasp-success"
    assert github_slug("Set-up") == "set-up"


def test_readme_is_short() -> None:
    size = len(README.read_bytes())
    assert size < 8192, f"README.md is {size} bytes; move detail into docs/"


def test_readme_links_every_docs_page() -> None:
    linked = {(README.parent / unquote(t.split("#")[0])).resolve() for t in links(README) if not t.startswith("#")}
    unlinked = [p.name for p in PAGES[1:] if p.resolve() not in linked]
    assert not unlinked, f"docs pages not linked from README.md: {unlinked}"


_FILE_PATH = re.compile(r"(?<![\w/.-])((?:sim|datagen|perception|grasping|posegrasp|assets|bench|tests)/[\w/.-]*\.(?:py|toml))\b")


@pytest.mark.parametrize("page", [p for p in PAGES if p.name != "perception_releases.md"],
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_named_source_files_exist(page: Path) -> None:
    """Source and settings files the docs name (`perception/plane.py`) exist; the release history may name old ones."""
    named = set(_FILE_PATH.findall(page.read_text(encoding="utf-8")))
    missing = sorted(p for p in named if not (ROOT / p).exists())
    assert not missing, f"{page.name} names files that do not exist: {missing}"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_links_resolve(page: Path) -> None:
    targets = links(page)
    assert targets or page != README, "README.md has no links"
    bad = []
    for target in targets:
        url = urlparse(target)
        if url.scheme in ("http", "https"):
            if not url.netloc or " " in target:
                bad.append(f"{target}: malformed URL")
            continue
        if url.scheme:  # mailto: and the like are not checked
            continue
        file = page if not url.path else (page.parent / unquote(url.path)).resolve()
        if not file.exists():
            bad.append(f"{target}: no file {file}")
            continue
        if url.fragment:
            if file.suffix != ".md":
                bad.append(f"{target}: anchor into a non-markdown file")
            elif unquote(url.fragment) not in anchors(file):
                bad.append(f"{target}: no heading #{url.fragment} in {file.name}")
    assert not bad, f"{page.name}: " + "; ".join(bad)


def test_module_map_matches_the_tree() -> None:
    """docs/architecture.md's module map names every module of each package (subpackages such as
    ``posegrasp.grasping.report`` in a section of their own), and only modules that exist."""
    text = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    section = text.split("## Where each concept lives", 1)[1]
    dirs = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["setuptools"]["package-dir"]
    dirs = {"posegrasp": "posegrasp", **dirs}
    problems = []
    for m in re.finditer(r"^\*\*`(posegrasp(?:\.\w+)*)`[^\n]*\*\*(.*?)(?=^\*\*`|\Z)", section, re.M | re.S):
        package, body = m.group(1), m.group(2)
        mapped = max((p for p in dirs if package == p or package.startswith(p + ".")), key=len)
        folder = ROOT / dirs[mapped] / Path(*package[len(mapped):].split(".")[1:])
        modules = {p.name for p in folder.glob("*.py") if p.name != "__init__.py"}
        if not modules:
            continue
        named = set(re.findall(r"`(\w+\.py)`", body)) | set(re.findall(r"(?<![\w/])(\w+\.py)\b", body))
        named = {n for n in named if not n.startswith("make_")}
        if named - modules:
            problems.append(f"{package} names missing modules {sorted(named - modules)}")
        if modules - named:
            problems.append(f"{package} leaves out {sorted(modules - named)}")
    assert not problems, "; ".join(problems)
    packages = set(re.findall(r"^\*\*`(posegrasp(?:\.\w+)?)`", section, re.M))
    assert {"posegrasp", "posegrasp.sim", "posegrasp.datagen", "posegrasp.perception", "posegrasp.grasping"} <= packages
