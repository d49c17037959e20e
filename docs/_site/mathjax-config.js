// MathJax 3 settings of the documentation site (docs/site.md), read before MathJax loads.
// Markdown pages: pymdownx.arithmatex wraps maths as \( \) / \[ \] inside class "arithmatex".
// Notebook pages (mkdocs-jupyter): markdown cells keep $ $ / $$ $$ inside "jp-RenderedMarkdown".
// The page body ("md-typeset") is skipped but for those two, so a stray $ in prose or a code
// output is left alone; the navigation (notebook headings with maths) is typeset.
window.MathJax = {
  tex: {
    inlineMath: [["\\(", "\\)"], ["$", "$"]],
    displayMath: [["\\[", "\\]"], ["$$", "$$"]],
    processEscapes: true,
    processEnvironments: true
  },
  options: {
    ignoreHtmlClass: "md-typeset",
    processHtmlClass: "arithmatex|jp-RenderedMarkdown"
  }
};
// Material's instant navigation swaps pages without reloading: typeset each new page.
if (typeof document$ !== "undefined") {
  document$.subscribe(() => {
    if (window.MathJax && MathJax.typesetPromise) {
      MathJax.startup.output.clearCache();
      MathJax.typesetClear();
      MathJax.texReset();
      MathJax.typesetPromise();
    }
  });
}
