// MathJax 3 configuration, read before javascripts/mathjax/tex-chtml.js (served from this site).
// Typesets the design pages' pymdownx.arithmatex spans (\( \) and \[ \]) and the tutorials'
// Markdown cells ($ $ and $$ $$, as Jupyter writes them); nothing else on a page. An element
// with any class is skipped with its subtree unless it is one of those two (processHtmlClass);
// inside them, elements without a class (p, li, em, table) are searched. (".*|" would also
// match the empty class of every nested <p> and skip the Markdown cells' paragraphs.)
window.MathJax = {
  tex: {
    inlineMath: [["\\(", "\\)"], ["$", "$"]],
    displayMath: [["\\[", "\\]"], ["$$", "$$"]],
    processEscapes: true,
    processEnvironments: true,
  },
  options: {
    ignoreHtmlClass: ".+",
    processHtmlClass: "arithmatex|jp-RenderedMarkdown",
  },
};

// With Material's instant navigation a new page arrives without a reload: typeset it again.
// The first page is typeset by MathJax's own start-up.
if (typeof document$ !== "undefined") {
  let firstPage = true;
  document$.subscribe(() => {
    if (firstPage) {
      firstPage = false;
      return;
    }
    window.MathJax.typesetClear();
    window.MathJax.texReset();
    window.MathJax.typesetPromise();
  });
}
