"""How the benchmark scripts report: each writes its part of RESULTS.md as it measures.

A script makes one :class:`Report`, adds headings, paragraphs, tables and figures with the
figures it measured, and saves it; ``run_all.py`` assembles the parts into
``benchmarks/RESULTS.md`` (or ``benchmarks/out/RESULTS-quick.md`` with ``--quick``), with the
machine, the date and a headline table built from the values each part records with
:meth:`Report.headline`. Everything is also printed as it comes, so a script run alone shows its
tables on the terminal.
"""

from __future__ import annotations

import json
import os
import textwrap
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
OUT = HERE / "out"


def parts_dir(quick: bool) -> Path:
    return OUT / ("report-quick" if quick else "report")


def figure_dir(quick: bool) -> Path:
    """Where figures go: ``docs/`` (shown in the README) in full mode; a scratch folder with
    ``--quick``, so that a check does not replace the published figures."""
    d = OUT / "quick-figures" if quick else ROOT / "docs"
    d.mkdir(parents=True, exist_ok=True)
    return d


def fmt(v, nd: int = 2) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return f"{v:.{nd + 1}f}" if abs(v) < 1 else f"{v:.{nd}f}"
    return str(v)


def faster(peer_s: float, ours_s: float) -> str:
    """'ours 3.1x faster' or 'ours 2.0x slower': a peer's time against ours, one wording."""
    r = peer_s / ours_s
    return f"ours {r:.1f}x faster" if r >= 1 else f"ours {1 / r:.1f}x slower"


def faster_range(peer_s: list[float], ours_s: list[float]) -> str:
    """'ours 2.2-2.4x faster' over several cases (or 'ours 1.5x slower to 2.0x faster')."""
    r = sorted(p / o for p, o in zip(peer_s, ours_s, strict=True))
    if r[0] >= 1:
        return f"ours {r[0]:.1f}-{r[-1]:.1f}x faster"
    if r[-1] < 1:
        return f"ours {1 / r[-1]:.1f}-{1 / r[0]:.1f}x slower"
    return f"{faster(r[0], 1.0)} to {faster(r[-1], 1.0)[5:]}"


class Report:
    """One script's part of RESULTS.md (``order`` sorts the parts)."""

    def __init__(self, name: str, order: int, title: str, command: str, quick: bool):
        self.name, self.order, self.quick = name, order, quick
        self.lines: list[str] = []
        self.heads: dict[str, dict] = {}
        cmd = command + (" --quick" if quick else "")
        self._add(f"## {title}\n\n`{cmd}`\n")

    def _add(self, text: str) -> None:
        self.lines.append(text)
        print(text, flush=True)

    def h(self, title: str) -> None:
        """A sub-heading (one per paper table or figure, or per measured case)."""
        self._add(f"### {title}\n")

    def p(self, text: str) -> None:
        """A paragraph (its lines dedented, so it may start on the line of the quotes)."""
        first, _, rest = text.strip("\n").partition("\n")
        self._add((first.strip() + "\n" + textwrap.dedent(rest)).strip() + "\n")

    def table(self, header: list[str], rows: list[list]) -> None:
        out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        out += ["| " + " | ".join(fmt(v) for v in row) + " |" for row in rows]
        self._add("\n".join(out) + "\n")

    def figure(self, png: Path, caption: str) -> None:
        rel = os.path.relpath(png, HERE)
        self._add(f"![{caption}]({rel})\n\n*{caption}* (`{os.path.relpath(png, ROOT)}`)\n")

    def headline(
        self,
        key: str,
        order: int,
        what: str,
        ours: str,
        paper: str = "",
        peer: str = "",
        target: str = "",
    ) -> None:
        """A row of the headline table at the top of RESULTS.md and in the README."""
        self.heads[key] = dict(
            order=order, what=what, ours=ours, paper=paper, peer=peer, target=target
        )

    def save(self) -> Path:
        parts = parts_dir(self.quick)
        parts.mkdir(parents=True, exist_ok=True)
        md = parts / f"{self.order:02d}-{self.name}.md"
        md.write_text("\n".join(self.lines))
        (parts / f"{self.order:02d}-{self.name}.json").write_text(json.dumps(self.heads, indent=1))
        return md
