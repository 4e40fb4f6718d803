"""Every ``docs/<page>.md#<anchor>`` reference in the code resolves to a page and a heading.

Docstrings cite the design pages in ``docs/`` by page and section. This checks them with the
standard library only (no mkdocs needed): the page must exist and, when an anchor is given, one
of its headings must produce that anchor under Python-Markdown's ``toc`` slug rule — the ids
``mkdocs build`` gives the headings. ``mkdocs build --strict`` (CI) checks the links inside the
pages themselves.
"""

from __future__ import annotations

import pathlib
import re
import unicodedata

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
SCANNED = [ROOT / "src", ROOT / "tests", ROOT / "benchmarks", ROOT / "examples", ROOT / "experiments"]
REFERENCE = re.compile(r"docs/((?:[\w-]+/)*[\w-]+\.md)(?:#([\w-]+))?")
FENCE = re.compile(r"^\s*(```|~~~)")
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")


def slugify(text: str, separator: str = "-") -> str:
    """Python-Markdown's ``toc`` default slugify (``markdown.extensions.toc.slugify``)."""
    text = unicodedata.normalize("NFKD", text).encode("ascii", "ignore").decode("ascii")
    text = re.sub(r"[^\w\s-]", "", text).strip().lower()
    return re.sub(rf"[{separator}\s]+", separator, text)


def heading_text(raw: str) -> str:
    """The text of a heading as rendered: inline code kept, emphasis and link syntax dropped."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", raw)  # [label](url) -> label
    return re.sub(r"[`*_]", "", text)


def anchors(page: pathlib.Path) -> set[str]:
    """The ids ``toc`` gives the page's headings (fenced code skipped; repeats get ``_1``, ``_2``...)."""
    ids: set[str] = set()
    in_fence = False
    for line in page.read_text(encoding="utf-8").splitlines():
        if FENCE.match(line):
            in_fence = not in_fence
            continue
        match = None if in_fence else HEADING.match(line)
        if match:
            slug = slugify(heading_text(match.group(2)))
            unique, n = slug, 0
            while unique in ids:
                n += 1
                unique = f"{slug}_{n}"
            ids.add(unique)
    return ids


def references() -> list[tuple[str, int, str, str | None]]:
    """(file, line, page, anchor) for every docs reference in the scanned code and the README."""
    files = [ROOT / "README.md"]
    for folder in SCANNED:
        if folder.is_dir():
            files += sorted(folder.rglob("*.py"))
    found = []
    for path in files:
        if path.resolve() == pathlib.Path(__file__).resolve():
            continue
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            for match in REFERENCE.finditer(line):
                found.append((str(path.relative_to(ROOT)), number, match.group(1), match.group(2)))
    return found


def test_slugify_matches_toc():
    assert slugify("Footprint and tiles") == "footprint-and-tiles"
    assert slugify("Blender (NeRF-synthetic)") == "blender-nerf-synthetic"
    assert slugify("Functional core, imperative shell") == "functional-core-imperative-shell"
    assert slugify("Standard 3DGS PLY") == "standard-3dgs-ply"


def test_the_code_cites_the_docs():
    # the references moved from the out-of-tree design file to docs/ (issue 23)
    assert len(references()) >= 20


@pytest.mark.parametrize("where, line, page, anchor", references(),
                         ids=lambda v: v if isinstance(v, str) else None)
def test_reference_resolves(where, line, page, anchor):
    target = DOCS / page
    assert target.is_file(), f"{where}:{line} cites docs/{page}, which does not exist"
    if anchor is not None:
        assert anchor in anchors(target), (
            f"{where}:{line} cites docs/{page}#{anchor}; the page's headings give {sorted(anchors(target))}")


def test_no_citation_of_the_out_of_tree_design_file():
    stale = [f"{path.relative_to(ROOT)}:{n}" for path in (ROOT / "src").rglob("*.py")
             for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1) if "DESIGN.md" in line]
    assert not stale, f"cite docs/<page>.md#<section> instead of DESIGN.md: {stale}"


API_PAGE = DOCS / "api.md"
#: what the page's first snippet's ``overrides`` becomes here: a 40x30 demo scene, 6 steps, growth and pruning
QUICK = ["train.iterations=6", "train.progress=false", "eval.every=3", "train.checkpoint_every=0",
         "grow.stats_start=1", "grow.start=4", "grow.stop=6", "grow.interval=2", "prune.start=2", "prune.interval=2",
         "eval.save_renders=false", "model.n_offsets=4", "model.latent_dim=8", "model.hidden=16",
         "model.appearance_dim=8", "features=none"]


def api_snippets() -> list[str]:
    """The ```python blocks of docs/api.md, in order."""
    return re.findall(r"^```python\n(.*?)^```", API_PAGE.read_text(encoding="utf-8"), flags=re.S | re.M)


@pytest.mark.slow  # four short trainings (about 2-4 min on 2 cores): .ci/run runs it with -m slow
def test_every_snippet_of_the_api_page_runs_as_written(tmp_path, tiny_scene, monkeypatch):
    """docs/api.md's how-to, executed in order in one namespace (in a fresh folder), with only its ``overrides``
    swapped for a short run on the tiny demo scene: a snippet that went stale fails here."""
    snippets = api_snippets()
    assert len(snippets) >= 7 and snippets[0].count("overrides = [") == 1
    first = re.sub(r"^overrides = \[[^\]]*\]", f"overrides = {[f'data.path={tiny_scene}', *QUICK]!r}", snippets[0],
                   count=1, flags=re.M)
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    for index, code in enumerate([first, *snippets[1:]]):
        exec(compile(code, f"docs/api.md snippet {index + 1}", "exec"), namespace)  # noqa: S102 - our own page
    record, own = namespace["record"], namespace["record_own"]
    assert set(namespace["record_tv"].loss_terms["mean"]) == {"l1", "ssim", "volume", "depth_tv"}
    assert namespace["record_pruned"].densify["prune_unseen"]["updates"] == 1
    assert float(np.max(np.abs(namespace["out"].image - namespace["same"].image))) < 1e-5  # vmap: float rounding
    assert own.loss_terms["steps"] == record.iterations and (tmp_path / "outputs" / "own_loop" / "eval.json").is_file()
