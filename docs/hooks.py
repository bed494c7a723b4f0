"""MkDocs hooks: links from a page to repository files outside docs/ (a benchmark's data, the examples, the
README) must name files that exist, and are shown as repository paths, since the site holds only docs/; and the
notebooks of examples/ are rendered where a page says `<!-- notebooks -->` (their cells, from the files)."""

from __future__ import annotations

import json
import re
from pathlib import Path

LINK = re.compile(r"(?<!!)\[([^\]]+)\]\(([^)\s#]+)(#[^)\s]*)?\)")
FENCE = re.compile(r"^(```|~~~)")


def on_page_markdown(markdown: str, page, config, files) -> str:
    docs = Path(config["docs_dir"]).resolve()
    repo = docs.parent
    if "<!-- notebooks -->" in markdown:
        markdown = markdown.replace("<!-- notebooks -->", rendered_notebooks(repo / "examples"))
    here = (docs / page.file.src_path).parent
    out, fenced = [], False
    for line in markdown.splitlines(keepends=True):
        if FENCE.match(line.strip()):
            fenced = not fenced
        if not fenced:
            line = LINK.sub(lambda m: _outside(m, here, docs, repo, page.file.src_path), line)
        out.append(line)
    return "".join(out)


def _outside(match: re.Match, here: Path, docs: Path, repo: Path, page: str) -> str:
    text, target = match.group(1), match.group(2)
    if "://" in target or target.startswith("mailto:"):
        return match.group(0)
    path = (here / target).resolve()
    if path == docs or docs in path.parents:
        return match.group(0)  # a page or file of the site: MkDocs checks it
    if repo not in path.parents or not path.exists():
        raise ValueError(f"{page}: link to {target}, which is not a file of the repository")
    return f"{text} (`{path.relative_to(repo).as_posix()}` in the repository)"


def rendered_notebooks(folder: Path) -> str:
    """Each notebook of `folder` as a section: its markdown cells as they are, its code cells as Python blocks
    (the notebooks are kept without outputs)."""
    parts = []
    for path in sorted(folder.glob("*.ipynb")):
        cells = json.loads(path.read_text())["cells"]
        parts.append(f"## {path.name}\n")
        for cell in cells:
            source = "".join(cell["source"]).strip()
            if cell["cell_type"] == "markdown":
                parts.append(re.sub(r"(?m)^#", "###", source, count=1) if source.startswith("# ") else source)
            elif cell["cell_type"] == "code":
                parts.append(f"```python\n{source}\n```")
    return "\n\n".join(parts) + "\n"
