"""MkDocs hooks of the documentation site (mkdocs.yml ``hooks:``; docs/site.md).

    on_config          clause headings get their id as anchor (``spec/stages.md#PRJ-04``); the
                       notebooks' kernels find ``_helpers`` and this checkout's refgs and oracle;
                       mkdocs-jupyter's cache is keyed by the sources the notebooks run
    on_files           MathJax 3 from the django-static-mathjax wheel under assets/mathjax/ (no
                       CDN: the pages render offline); the repository files that pages link
                       outside docs/ (CHANGELOG.md, experiments/*.toml) under repo/
    on_page_markdown   those links rewritten to the copies under repo/
    on_post_page       a notebook page loses nbconvert's MathJax 2 tags (an empty ``src`` and a
                       MathJax 2 configuration): the site's MathJax 3 typesets it
"""
from __future__ import annotations

import hashlib
import importlib.resources
import os
import posixpath
import re
from pathlib import Path

from markdown.extensions.toc import slugify
from mkdocs.structure.files import File

#: The repository root (mkdocs.yml's folder) and the docs folder.
ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
#: A clause heading's text (docs/spec/README.md "Clause format"; oracle/clauses.py CLAUSE_HEADING).
CLAUSE = re.compile(r"^([A-Z]{2,4}-\d{2}):")
#: Where the copies of repository files linked from outside docs/ go in the site.
REPO_PREFIX = "repo"
#: Where MathJax goes in the site (mkdocs.yml extra_javascript names its entry script there).
MATHJAX_PREFIX = "assets/mathjax"
#: The parts of MathJax 3's es5 folder the tex-mml-chtml component loads: the entry script, the
#: TeX extensions it autoloads, the CommonHTML fonts, the menu (the speech engine and the other
#: combined components are left out).
MATHJAX_PARTS = ("tex-mml-chtml.js", "input", "output/chtml", "output/chtml.js", "ui", "a11y",
                 "adaptors")
#: Sources whose change must execute the notebooks again (mkdocs-jupyter's cache key covers only
#: the notebook file itself).
NOTEBOOK_INPUTS = ("refgs", "oracle", "docs/notebooks/_helpers.py", "docs/_site/hooks.py")
#: matplotlib's backend in the notebooks' kernels: Jupyter's inline one, figures as PNG outputs.
INLINE_BACKEND = "module://matplotlib_inline.backend_inline"
#: Set (to anything) for a preview that shows the notebooks without executing them.
NO_EXECUTE_VARIABLE = "REFGS_DOCS_NO_EXECUTE"
#: nbconvert's MathJax 2 tags in a notebook page (mkdocs-jupyter passes an empty script URL).
NBCONVERT_MATHJAX = re.compile(r'<script src="">\s*</script>|<script type="text/x-mathjax-config">.*?</script>',
                               re.S)
#: An inline Markdown link's target (no spaces; titles are not used in these docs).
LINK = re.compile(r"(\]\()([^)\s]+)(\))")


def clause_slugify(value: str, separator: str, unicode: bool = False) -> str:
    """The anchor of a heading: a clause's id (``PRJ-04``), else Python-Markdown's slug."""
    m = CLAUSE.match(value.strip())
    return m.group(1) if m else slugify(value, separator, unicode)


def sources_digest(paths=NOTEBOOK_INPUTS) -> str:
    """sha256 (16 hex digits) of the Python sources under ``paths`` (relative to ROOT)."""
    h = hashlib.sha256()
    for rel in paths:
        p = ROOT / rel
        for f in sorted([p] if p.is_file() else p.rglob("*.py")):
            h.update(str(f.relative_to(ROOT)).encode())
            h.update(f.read_bytes())
    return h.hexdigest()[:16]


def on_config(config):
    config.mdx_configs.setdefault("toc", {})["slugify"] = clause_slugify
    jupyter = config.plugins.get("mkdocs-jupyter")
    if jupyter is not None:
        jupyter.config["cache_dir"] = str(ROOT / ".cache" / "mkdocs-jupyter" / sources_digest())
        if os.environ.get(NO_EXECUTE_VARIABLE):          # a quick preview, never the CI build
            jupyter.config["execute"] = False
    # the kernels inherit this environment: this checkout first, then the notebooks' _helpers
    # (tests/test_notebooks.py sets the same); figures go into the page (an MPLBACKEND such as
    # Agg set for the tests would draw them nowhere)
    extra = [str(ROOT), str(DOCS / "notebooks")]
    os.environ["PYTHONPATH"] = os.pathsep.join(
        extra + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p])
    os.environ["MPLBACKEND"] = INLINE_BACKEND
    return config


def _mathjax_files(config) -> list[File]:
    try:
        es5 = importlib.resources.files("mathjax") / "static" / "mathjax" / "es5"
    except ModuleNotFoundError:
        raise SystemExit("docs: MathJax is missing: pip install -e '.[docs]' "
                         "(django-static-mathjax)") from None
    es5 = Path(str(es5))
    out = []
    for part in MATHJAX_PARTS:
        p = es5 / part
        for f in sorted([p] if p.is_file() else (q for q in p.rglob("*") if q.is_file())):
            out.append(File.generated(config, f"{MATHJAX_PREFIX}/{f.relative_to(es5).as_posix()}",
                                      abs_src_path=str(f)))
    return out


def outside_target(page_src: str, target: str) -> str | None:
    """The repository path (posix, relative to ROOT) a link of page ``page_src`` (relative to
    docs/) points to when it leaves docs/, else None."""
    if re.match(r"^[a-z]+:", target) or target.startswith(("#", "/")):
        return None
    path = target.split("#", 1)[0]
    joined = posixpath.normpath(posixpath.join("docs", posixpath.dirname(page_src), path))
    if joined.startswith("docs/") or joined.startswith("..") or not (ROOT / joined).is_file():
        return None
    return joined


def _outside_links(files) -> set[str]:
    found = set()
    for f in files.documentation_pages():
        if f.abs_src_path and f.src_uri.endswith(".md"):
            text = Path(f.abs_src_path).read_text(encoding="utf-8")
            found |= {t for _, target, _ in LINK.findall(text)
                      if (t := outside_target(f.src_uri, target))}
    return found


def on_files(files, config):
    for f in _mathjax_files(config):
        files.append(f)
    for rel in sorted(_outside_links(files)):
        files.append(File.generated(config, f"{REPO_PREFIX}/{rel}", abs_src_path=str(ROOT / rel)))
    return files


def on_page_markdown(markdown, page, config, files):
    src = page.file.src_uri

    def fix(m):
        rel = outside_target(src, m.group(2))
        if rel is None:
            return m.group(0)
        anchor = m.group(2)[len(m.group(2).split("#", 1)[0]):]
        new = posixpath.relpath(f"{REPO_PREFIX}/{rel}", posixpath.dirname(src) or ".")
        return f"{m.group(1)}{new}{anchor}{m.group(3)}"

    return LINK.sub(fix, markdown)


def on_post_page(output, page, config):
    return NBCONVERT_MATHJAX.sub("", output)
