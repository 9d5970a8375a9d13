"""README.md and the hand-written docs pages are text for users: no development history.

Hand-written snippets under ``docs/snippets/`` (included into pages with ``--8<--``) count as
pages. Generated text (``bench tables``' ``table*.md``, the snippets that commands write) and
the CHANGELOG are exempt: the changelog is where dated history belongs.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
# Written by commands (bench leaderboard, bench methods, benchmarks/compute_accounting.py);
# every other snippet is hand-written and held to the rules of a page.
GENERATED_SNIPPETS = {DOCS / "snippets" / name
                      for name in ("leaderboard.md", "methods_table.md", "compute_measured.md")}
_INCLUDE = re.compile(r'^--8<-- "(docs/snippets/[^":]+)"', re.MULTILINE)

# Each pattern names what it catches; a hit is reported with its file and line.
_HEX = r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b"
_TIMING = r"\b\d+(?:[.,]\d+)?\s?(?:ms|s|min|h|minutes|seconds|hours)\b"
PATTERNS = {
    "issue number": re.compile(r"\bissues?\s+#?\d+", re.IGNORECASE),
    "#N reference": re.compile(r"(?<![\w&/])#\d+\b"),
    "machine path": re.compile(r"(?<![\w.])/(?:work|tmp|root|home)/"),
    "brief": re.compile(r"\bbriefs?\b", re.IGNORECASE),
    "ISO date": re.compile(r"\b(?:19|20)\d{2}-[01]\d-[0-3]\d\b"),
    "session note": re.compile(r"\bthis session\b|\(test\)", re.IGNORECASE),
    "commit stamp": re.compile(r"\bcommits?\s+`?" + _HEX),
    "commit hash next to a timing": re.compile(
        rf"{_HEX}.*{_TIMING}|{_TIMING}.*{_HEX}"),
    "release narrative": re.compile(r"\bthis release\b|\bthe first (?:\S+ )?runs\b",
                                    re.IGNORECASE),
}


def user_pages() -> list[Path]:
    """README.md and every hand-written Markdown page and snippet under docs/."""
    generated = {DOCS / "changelog.md"}          # includes the CHANGELOG, which is exempt
    generated |= set((DOCS / "results").glob("table*.md")) | GENERATED_SNIPPETS
    pages = [p for p in sorted(DOCS.rglob("*.md")) if p not in generated]
    return [REPO / "README.md"] + pages


def history_hits(text: str) -> list[tuple[int, str, str]]:
    """(line number, pattern name, line) for every line that holds development history."""
    return [(n, name, line.strip())
            for n, line in enumerate(text.splitlines(), 1)
            for name, pattern in PATTERNS.items() if pattern.search(line)]


@pytest.mark.parametrize("planted", [
    "As issue 15 asked, the default changed.",
    "Fixed in #42.",
    "The run wrote /work/diag/hil_s1 and /tmp/act15/state.pt.",
    "The cache lives in /root/.cache and /home/me/runs.",
    "Written as the brief asks.",
    "Measured on 2026-12-02 on the 2-core machine.",
    "During this session the grid finished.",
    "The oracle replays the demo (test).",
    "Measured at commit `5fb35dc`.",
    "The suite ran in 5 min 46 s (b2f7456).",
    "The wedging cue needs contact since this release.",
    "### The first `cpu`-profile runs",
])
def test_patterns_catch_planted_history(planted):
    assert history_hits(f"A clean line.\n{planted}\n"), planted


@pytest.mark.parametrize("clean", [
    "See [Info](environments.md#info) and [the seeds protocol](tables.md#the-evaluation-seeds-protocol).",
    "The grasp critic's loss is `(Q_g(s, c) - y_g)²`; h = 10 at 10 Hz is 1.0 s.",
    "A 2 x 256 MLP took 78 ms per step; sha256 over the file's content.",
    "`tests/test_act.py` keeps the file under 1,000,000 bytes, briefly.",
])
def test_patterns_leave_user_text_alone(clean):
    assert not history_hits(clean)


def test_user_pages_hold_no_development_history():
    hits = [f"{p.relative_to(REPO)}:{n}: {name}: {line}"
            for p in user_pages() for n, name, line in history_hits(p.read_text())]
    assert not hits, "development history in user-facing text:\n" + "\n".join(hits)


def _words(path: Path) -> int:
    return len(path.read_text().split())


def rendered_words(page: Path) -> int:
    """Words of the page as rendered: its own plus those of the hand-written snippets it
    includes (a generated snippet is as long as its command makes it)."""
    included = [REPO / name for name in _INCLUDE.findall(page.read_text())]
    return _words(page) + sum(_words(s) for s in included if s not in GENERATED_SNIPPETS)


def test_rendered_words_count_hand_written_snippets_only():
    # harness.md includes the generated methods table and the hand-written measurements
    page, snippets = DOCS / "harness.md", DOCS / "snippets"
    assert rendered_words(page) == _words(page) + _words(snippets / "harness_measured.md")


def test_every_snippet_is_checked_or_generated():
    snippets = set((DOCS / "snippets").glob("*.md"))
    assert GENERATED_SNIPPETS <= snippets, "a generated snippet was renamed or removed"
    unchecked = snippets - GENERATED_SNIPPETS - set(user_pages())
    assert not unchecked, unchecked
    assert DOCS / "snippets" / "harness_measured.md" in user_pages()


def test_pages_are_short_enough_to_read():
    limits = {p: 4000 for p in user_pages()[1:]}
    limits[DOCS / "results" / "index.md"] = 1500
    limits.update({p: 400 for p in (DOCS / "results" / "diagnoses").glob("*.md")})
    limits.update({p: 600 for p in (DOCS / "snippets").glob("*.md")
                   if p not in GENERATED_SNIPPETS})
    too_long = [f"{p.relative_to(REPO)}: {rendered_words(p)} words with its snippets "
                f"(at most {n})" for p, n in limits.items() if rendered_words(p) > n]
    assert not too_long, "\n".join(too_long)
    lines = len((REPO / "README.md").read_text().splitlines())
    assert lines <= 120, f"README.md: {lines} lines (at most 120)"


# CI runs the first line under each of these README headings verbatim.
README_COMMANDS = {
    "## Run the main job": "pip install torch==2.13.0 && pip install -e . && bench run --method "
                           "qcfql --env WindowInstall-A-v0 --profile smoke --out runs/smoke-qcfql "
                           "--resume",
    "## Run the tests": 'pip install torch==2.13.0 && pip install -e ".[test]" && '
                        "python -m pytest -q tests",
}


def test_readme_keeps_the_commands_ci_runs():
    lines = (REPO / "README.md").read_text().splitlines()
    for heading, command in README_COMMANDS.items():
        assert heading in lines, f"README.md lost the heading {heading!r}"
        rest = [ln for ln in lines[lines.index(heading) + 1:] if ln.strip()]
        assert rest[:2] == ["```bash", command], f"README.md: {heading} must open with {command!r}"


def test_readme_lists_every_subcommand():
    from window_bench.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    readme = (REPO / "README.md").read_text()
    missing = [name for name in sub.choices if f"`bench {name}" not in readme]
    assert not missing, f"README.md's command table lacks: {missing}"
