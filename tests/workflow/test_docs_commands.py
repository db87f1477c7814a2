"""The snakemake command lines printed in the docs work as printed.

``--configfile``, ``--config`` and ``--forcerun`` take several values, so a line such as
``snakemake --cores 2 --configfile my.yaml reproduce`` reads ``reproduce`` as a second config file
(and then dies).  Every documented line is parsed with Snakemake's own argument parser and checked
for what it obviously means: its last word is a target, config files are YAML files, forced rules
are rule names.  One documented line also runs for real, as a dry run against a config written here.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[2]
SNAKEMAKE = shutil.which("snakemake", path=str(Path(sys.executable).parent)) or shutil.which("snakemake")

pytestmark = pytest.mark.skipif(SNAKEMAKE is None, reason="snakemake is not installed")

# files whose snakemake lines a user copies: the docs (code blocks and inline code) and the comments
# at the top of the Snakefile, the configs and the profiles
DOC_FILES = [REPO / "README.md", REPO / "config" / "README.md", *sorted((REPO / "docs").glob("*.md"))]
COMMENT_FILES = [REPO / "Snakefile", *sorted((REPO / "config").glob("*.yaml")),
                 *sorted((REPO / "workflow" / "profiles").glob("*/config.yaml"))]


def rule_names() -> set[str]:
    names = set()
    for path in [REPO / "Snakefile", *sorted((REPO / "rules").glob("*.smk"))]:
        names.update(re.findall(r"^rule (\w+):", path.read_text(), flags=re.M))
    return names


def documented_lines() -> list[tuple[str, str]]:
    """(where, command line) of every snakemake invocation in the docs and the file comments."""
    found = []
    for path in DOC_FILES:
        text = path.read_text()
        for k, line in enumerate(text.splitlines(), 1):
            stripped = line.strip()
            if line.startswith("    ") and stripped.startswith("snakemake "):  # indented code block
                found.append((f"{path.name}:{k}", stripped))
        text_no_blocks = re.sub(r"```.*?```", "", text, flags=re.S)
        for m in re.finditer(r"`(snakemake [^`]+)`", text_no_blocks):  # inline code, may wrap lines
            k = text.count("\n", 0, text.find(m.group(0))) + 1
            found.append((f"{path.name}:{k}", " ".join(m.group(1).split())))
        for block in re.findall(r"```[^\n]*\n(.*?)```", text, flags=re.S):  # fenced blocks
            found += [(path.name, ln.strip()) for ln in block.splitlines() if ln.strip().startswith("snakemake ")]
    for path in COMMENT_FILES:
        for k, line in enumerate(path.read_text().splitlines(), 1):
            m = re.match(r"#.*?(snakemake (?:--|-\w|\w).*?)`?\s*$", line)
            if m and "pip install" not in line:
                found.append((f"{path.relative_to(REPO)}:{k}", m.group(1).rstrip("`) ")))
    return found


def parse(line: str):
    """Snakemake's own parse of ``line`` (a trailing ``# comment`` dropped)."""
    from snakemake.cli import get_argument_parser

    argv = shlex.split(line, comments=True)
    assert argv[0] == "snakemake", line
    return argv, get_argument_parser().parse_args(argv[1:])


def check_line(line: str, rules: set[str]) -> None:
    """Assert that ``line`` means what it plainly says; AssertionError naming the problem otherwise."""
    argv, args = parse(line)
    targets = list(args.targets or [])
    if not argv[-1].startswith("-"):
        assert argv[-1] in targets, f"{line!r}: its last word {argv[-1]!r} is not a target (targets: {targets})"
    for target in targets:
        assert target in rules or target.startswith("results/"), f"{line!r}: target {target!r} is no rule or output"
    for path in args.configfile or []:
        assert Path(path).suffix in (".yaml", ".yml"), f"{line!r}: {str(path)!r} is read as a config file"
    for rule in args.forcerun or []:
        assert rule in rules, f"{line!r}: {rule!r} is read as a rule to force"
    for item in args.config or []:
        assert "=" in item, f"{line!r}: {item!r} is read as a config KEY=VALUE"


def test_docs_have_command_lines():
    lines = documented_lines()
    where = {w.split(":")[0] for w, _ in lines}
    # the extractor finds the README's block and inline lines, docs/datasets.md's and the comments
    assert len(lines) >= 10, lines
    assert {"README.md", "datasets.md", "Snakefile", "config/replica.yaml"} <= where, where
    assert any("--configfile" in line for _, line in lines)


@pytest.mark.parametrize("where, line", documented_lines())
def test_documented_line_parses_as_intended(where, line):
    check_line(line, rule_names())


@pytest.mark.parametrize(
    "line",
    [
        "snakemake --cores 2 --configfile my.yaml reproduce",  # the README's old line
        "snakemake --cores 2 --configfile config/replica.yaml reproduce",  # docs/datasets.md's old line
        "snakemake --cores 2 --forcerun gaussians results/room1/gaussians",  # forcerun swallows the target
        "snakemake --cores 2 --config seed=1 reproduce",
    ],
)
def test_check_catches_swallowed_targets(line):
    with pytest.raises(AssertionError):
        check_line(line, rule_names())


def test_documented_configfile_line_dry_runs(tmp_path):
    """The README's own-config line, as printed, plus -n and the Snakefile's path: the DAG it makes."""
    line = next(line for _, line in documented_lines() if "--configfile=my.yaml" in line)
    results = tmp_path / "out"
    (tmp_path / "my.yaml").write_text(yaml.safe_dump({
        "results": str(results),
        "scenes": {"mine": {"kind": "synthetic", "synthetic": {"seed": 3, "num_views": 6}}},
    }))
    argv = shlex.split(line, comments=True)
    cmd = [SNAKEMAKE, *argv[1:], "-n", "--snakefile", str(REPO / "Snakefile")]
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    result = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, env=env, timeout=180)
    out = result.stdout + result.stderr
    assert result.returncode == 0, out
    assert "scene=mine" in out and f"{results}/mine/gaussians" in out, out
    assert "room0" not in out  # the user's scene list replaces the default one
    assert not results.exists()  # a dry run


# ----------------------------------------------------------------------------------------------
# The README's paths exist: every link, and every `path` in code spans and blocks that names a file
# or folder of the checkout (what the pipeline writes under results/ aside, but results/README.md)
# ----------------------------------------------------------------------------------------------


def readme_paths(text: str) -> set[str]:
    found = {m.group(1).split("#")[0] for m in re.finditer(r"\]\(([^)\s]+)\)", text)
             if not re.match(r"(https?:|#|mailto:)", m.group(1))}
    tops = {p.name for p in REPO.iterdir()} - {".git"}
    spans = re.findall(r"`([^`\n]+)`", text) + [ln for ln in text.splitlines() if ln.startswith("    ")]
    for span in spans:
        for word in re.findall(r"[\w.\-]+(?:/[\w.\-*<>{}]*)+|[\w\-]+\.(?:md|yaml|toml|py|txt)\b", span):
            word = word.rstrip(".,;:")
            if word.split("/")[0] not in tops or any(c in word for c in "*<>{}$"):
                continue
            if word.startswith("results/") and word != "results/README.md":
                continue  # written by the pipeline
            found.add(word)
    return found


def test_every_path_the_readme_names_exists():
    paths = readme_paths((REPO / "README.md").read_text())
    assert {"docs/results.md", "config/config.yaml", "LICENSE", "results/README.md"} <= paths, sorted(paths)
    missing = sorted(p for p in paths if not (REPO / p).exists())
    assert missing == [], f"README.md names paths that do not exist: {missing}"


def test_the_path_check_sees_a_missing_path():
    paths = readme_paths("see [the notes](docs/no-such-page.md) and `config/gone.yaml`; `results/room0/x` is made")
    assert paths == {"docs/no-such-page.md", "config/gone.yaml"}
    assert not any((REPO / p).exists() for p in paths)


# ----------------------------------------------------------------------------------------------
# No dated figures in the library: a date in a docstring or comment goes stale; measurements with
# their dates belong in docs/history/ (docs/performance.md has the current figures)
# ----------------------------------------------------------------------------------------------

DATE = re.compile(r"\b20\d\d-[01]\d-[0-3]\d\b")
# files that still carry one, being changed elsewhere when this check came; remove an entry with its date
DATED_FOR_NOW: set[str] = set()


def dated_files(root: Path) -> set[str]:
    return {str(p.relative_to(REPO)) for p in sorted(root.rglob("*.py")) if DATE.search(p.read_text())}


def test_no_library_file_carries_a_date():
    dated = dated_files(REPO / "trace3d")
    assert dated - DATED_FOR_NOW == set(), "move the dated figures to docs/history/ and say what is true now"
    assert DATED_FOR_NOW <= dated, f"no date left in {sorted(DATED_FOR_NOW - dated)}: drop it from DATED_FOR_NOW"


def test_the_date_check_sees_a_date():
    assert DATE.search("# 1.3x faster (measured 2026-11-26 on the 2-core machine)")
    assert not DATE.search("threads: 1  # 2 threads per job; seed 20260 of 2026 rooms")


def test_the_front_door_stays_short():
    """docs/results.md and docs/history/ take the tables and the dated record; these pages stay readable."""
    limits = {"README.md": 130, "docs/performance.md": 150}
    over = {name: n for name, limit in limits.items()
            if (n := len((REPO / name).read_text().splitlines())) > limit}
    assert over == {}, f"lines over the limit {limits}: {over}"
