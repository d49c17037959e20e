"""The documentation site (mkdocs.yml, docs/site.md).

Default run (cheap, static): every page under docs/ is in the navigation (the strict build fails
on one that is not), every module of refgs/ and oracle/ is on an API page, clause headings get
their id as anchor.  Marker ``browser``: the site is built strictly (``mkdocs build``, the
notebooks executed or taken from the build's cache), then headless Chromium opens the landing
page and a notebook page: the maths must be typeset by MathJax (``mjx-container`` elements, from
the site's own copy: the pages load nothing from another host) and the notebook's figures drawn;
the screenshots are kept in the test's temporary folder (their paths are printed).
"""
from __future__ import annotations

import base64
import importlib.util
import io
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
#: the headless browser of Debian's ``chromium`` package
CHROMIUM = Path("/usr/bin/chromium")
#: Chromium's flags for a reproducible offline page load (no sandbox: CI runs as root)
CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync", "--no-first-run",
                  "--hide-scrollbars")
#: virtual milliseconds Chromium gives the page's scripts (MathJax typesets the spec pages in
#: about one real second here)
VIRTUAL_TIME_MS = 20000
#: the notebook page the browser test opens (five figures)
NOTEBOOK_PAGE = "notebooks/01_one_gaussian/index.html"
#: a rendered page or figure has at least this many distinct colours; a blank one has a few
MIN_COLOURS = 50


def load_hooks():
    spec = importlib.util.spec_from_file_location("docs_site_hooks", DOCS / "_site" / "hooks.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def mkdocs_config() -> dict:
    yaml = pytest.importorskip("yaml", reason="the docs extra (pip install -e '.[docs]')")
    return yaml.safe_load((ROOT / "mkdocs.yml").read_text(encoding="utf-8"))


def nav_entries(nav) -> list[str]:
    out = []
    for entry in nav:
        values = entry.values() if isinstance(entry, dict) else [entry]
        for v in values:
            out += nav_entries(v) if isinstance(v, list) else [v]
    return out


# --- default run: the site's sources ------------------------------------------------------------
def test_every_page_is_in_the_navigation():
    cfg = mkdocs_config()
    nav = set(nav_entries(cfg["nav"]))
    pages = {p.relative_to(DOCS).as_posix() for p in DOCS.rglob("*.md")}
    notebooks = {p.relative_to(DOCS).as_posix() for p in (DOCS / "notebooks").glob("[0-9][0-9]_*.py")}
    missing = sorted((pages | notebooks) - nav)
    assert not missing, f"add to mkdocs.yml nav (the strict build fails without them): {missing}"
    generated = {e for e in nav if e.startswith(load_hooks().REPO_PREFIX + "/")}
    assert not sorted(nav - pages - notebooks - generated), "nav names pages that do not exist"


def test_every_module_is_on_an_api_page():
    named, recursive = set(), set()
    for page in (DOCS / "api").glob("*.md"):
        for m in re.finditer(r"^::: ([\w.]+)\n((?:    .*\n)*)", page.read_text(encoding="utf-8"), re.M):
            (recursive if "show_submodules: true" in m.group(2) else named).add(m.group(1))
    missing = []
    for pkg in ("refgs", "oracle"):
        for path in sorted((ROOT / pkg).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            if any(p.startswith("_") and p != "__init__" for p in parts):
                continue                                 # private modules, __main__
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            if name in named or any(name == r or name.startswith(r + ".") for r in recursive):
                continue
            if name in ("refgs", "oracle") and name in named | recursive:
                continue
            missing.append(name)
    assert not missing, f"modules on no page of docs/api/ (add '::: name'): {missing}"


def test_clause_headings_are_anchored_by_their_id():
    hooks = load_hooks()
    assert hooks.clause_slugify("PRJ-04: Dilation of the 2D covariance", "-") == "PRJ-04"
    assert hooks.clause_slugify("The $-0.5$ that is not a bug", "-") == "the-05-that-is-not-a-bug"
    assert hooks.outside_target("spec/README.md", "../../CHANGELOG.md") == "CHANGELOG.md"
    assert hooks.outside_target("sweeps.md", "../experiments/paper_main.toml") == \
        "experiments/paper_main.toml"
    assert hooks.outside_target("index.md", "spec/stages.md#PRJ-04") is None
    assert hooks.outside_target("index.md", "https://example.org/x.md") is None


# --- browser: the built site in headless Chromium ----------------------------------------------
def chromium(args: list, profile: Path) -> subprocess.CompletedProcess:
    return subprocess.run([str(CHROMIUM), *CHROMIUM_FLAGS, f"--user-data-dir={profile}",
                           f"--virtual-time-budget={VIRTUAL_TIME_MS}", *args],
                          capture_output=True, text=True, timeout=300, check=False)


def colours(png: bytes) -> int:
    from PIL import Image
    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))
    return np.unique(img.reshape(-1, 3), axis=0).shape[0]


@pytest.fixture(scope="module")
def built_site(tmp_path_factory):
    pytest.importorskip("mkdocs", reason="the docs extra (pip install -e '.[docs]')")
    site = tmp_path_factory.mktemp("site")
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--site-dir", str(site)],
                       cwd=ROOT, capture_output=True, text=True, timeout=1800)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    return site


@pytest.mark.browser
@pytest.mark.parametrize("page, figures", [("index.html", 0), (NOTEBOOK_PAGE, 1)],
                         ids=["landing", "notebook"])
def test_page_renders_maths_and_figures_offline(built_site, tmp_path, page, figures):
    if not CHROMIUM.exists():
        pytest.skip(f"{CHROMIUM} is absent (Debian: apt-get install chromium)")
    html = (built_site / page).read_text(encoding="utf-8")
    remote = re.findall(r'<(?:script|img)[^>]+src="(https?:[^"]+)"', html) + re.findall(
        r'<link[^>]+rel="stylesheet"[^>]+href="(https?:[^"]+)"', html)
    assert not remote, f"{page} loads from another host: {remote}"
    url = (built_site / page).as_uri()
    dom = chromium(["--dump-dom", url], tmp_path / "profile-dom").stdout
    assert dom.count("<mjx-container") >= 1, f"{page}: MathJax typeset nothing"
    assert "<mjx-merror" not in dom, f"{page}: MathJax could not parse some maths"
    if figures:
        pngs = re.findall(r'<img[^>]+src="data:image/png;base64,([^"]+)"', dom)
        assert len(pngs) >= figures, f"{page}: no figure in the executed notebook"
        assert max(colours(base64.b64decode(p)) for p in pngs) >= MIN_COLOURS, "blank figures"
    shot = tmp_path / f"{Path(page).parent.name or 'landing'}.png"
    chromium(["--window-size=1280,2600", f"--screenshot={shot}", url], tmp_path / "profile-shot")
    assert shot.is_file(), "chromium wrote no screenshot"
    print(f"screenshot: {shot}")
    assert colours(shot.read_bytes()) >= MIN_COLOURS
