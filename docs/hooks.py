"""MkDocs hooks (mkdocs.yml): the benchmark results and the changelog, which live beside the
code (benchmarks/RESULTS.md, CHANGELOG.md), are pages of the site too, their links rewritten
for where the pages sit in it."""

from __future__ import annotations

from pathlib import Path

from mkdocs.structure.files import File

ROOT = Path(__file__).resolve().parents[1]


def on_files(files, config):
    results = (ROOT / "benchmarks" / "RESULTS.md").read_text()
    files.append(File.generated(config, "results.md", content=results.replace("](../docs/", "](")))
    changelog = (ROOT / "CHANGELOG.md").read_text()
    changelog = changelog.replace("](benchmarks/RESULTS.md)", "](results.md)")
    files.append(File.generated(config, "changelog.md", content=changelog))
    return files
