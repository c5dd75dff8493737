// Fold the solution cells of the tutorials: a code cell whose first line is "# Solution"
// is wrapped in a <details> element, so readers try the exercise before opening it.
function foldSolutions() {
  document.querySelectorAll(".jp-CodeCell").forEach(function (cell) {
    if (cell.dataset.folded) return;
    var pre = cell.querySelector(".jp-InputArea pre, .highlight-ipynb pre");
    if (!pre || !pre.textContent.trim().startsWith("# Solution")) return;
    var details = document.createElement("details");
    details.className = "mslam-solution";
    var summary = document.createElement("summary");
    summary.textContent = "Solution (try the exercises first)";
    details.appendChild(summary);
    cell.parentNode.insertBefore(details, cell);
    details.appendChild(cell);
    cell.dataset.folded = "1";
  });
}
if (typeof document$ !== "undefined") {
  document$.subscribe(foldSolutions);  // Material's instant navigation
} else {
  document.addEventListener("DOMContentLoaded", foldSolutions);
}
