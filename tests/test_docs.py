"""The README and the documentation site: the site builds with `mkdocs build --strict`, every
link and image in README.md and docs/ resolves, the README stays short, and its test command is
the one CI runs."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md"] + sorted((ROOT / "docs").glob("*.md"))
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
SNIPPET = re.compile(r'^--8<-- "([^"]+)"', re.M)


def _targets(page):
    text = page.read_text()
    text = re.sub(r"```.*?```", "", text, flags=re.S)  # links inside code blocks are code
    return [m.group(1) for m in LINK.finditer(text)]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_links_and_images_resolve(page):
    """Every relative link and image of the page names an existing file (anchors stripped), and
    every snippet it includes exists."""
    missing = []
    for target in _targets(page):
        if re.match(r"^[a-z]+://|^mailto:", target):
            continue
        path = target.split("#")[0]
        if path and not (page.parent / path).exists():
            missing.append(target)
    for snippet in SNIPPET.findall(page.read_text()):
        if not (ROOT / "docs" / snippet).exists():
            missing.append(snippet)
    assert not missing, f"{page.relative_to(ROOT)}: missing {missing}"


def test_readme_is_short_and_has_the_ci_command():
    """At most about 10 KB; its second command (the tests) is exactly what .ci/run runs, and its
    first installs the package and runs the main job."""
    text = (ROOT / "README.md").read_text()
    assert len(text.encode()) <= 10_500, len(text.encode())
    blocks = re.findall(r"```\n(.*?)\n```", text, flags=re.S)
    main, tests = blocks[0].strip(), blocks[1].strip()
    assert "pip install" in main and "jaxoptics fit --example" in main
    ci = [line for line in (ROOT / ".ci" / "run").read_text().splitlines() if line.strip() and not line.startswith("#")]
    assert tests in ci, (tests, ci)


def test_site_builds_strict(tmp_path):
    """`mkdocs build --strict` (broken links, missing snippets, API pages that fail to render: all
    errors) succeeds, and the API reference renders every public name."""
    res = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-q", "-d", str(tmp_path / "site")],
                         cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout + res.stderr
    api = (tmp_path / "site" / "api" / "index.html").read_text()
    import jaxoptics as jo

    public = jo.__all__
    absent = [n for n in public if f'id="jaxoptics.{n}"' not in api]
    assert not absent, absent


@pytest.mark.slow
def test_readme_python_examples_run(tmp_path):
    """The README's Python blocks, run in order in a fresh process (as a user would paste them), in
    an empty directory (the figure they save lands there)."""
    text = (ROOT / "README.md").read_text()
    code = "\n".join(re.findall(r"```python\n(.*?)```", text, flags=re.S))
    res = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    assert (tmp_path / "fit.png").stat().st_size > 20000
    assert (tmp_path / "index_fit.png").stat().st_size > 20000


def test_home_page_lists_every_page_of_the_site():
    """Every page of the site's navigation (mkdocs.yml) is linked from the home page's table, so the
    home page shows every area the package covers."""
    nav = re.findall(r"^\s*- [^:]+: (\S+\.md)$", (ROOT / "mkdocs.yml").read_text(), flags=re.M)
    home = _targets(ROOT / "docs" / "index.md")
    assert len(nav) >= 10
    missing = [page for page in nav if page != "index.md" and page not in home]
    assert not missing, missing
