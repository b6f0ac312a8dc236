"""Are fbspost's outputs byte-identical at a base revision and in this working tree? (refactors)

Run from the repository root:  python bench/identical.py [--base REV] [--head REV] [--quick] [--jobs N]

Compensates every program of ``tests/data``, ``samples`` and the shared corpus (``$FBSPOST_CORPUS``,
else ``../shared/corpus`` beside the repository, skipped when absent) with the code of REV (default
``main``; ``git archive`` of it into a temporary directory) and with the code of this working tree
(or of ``--head REV``), each through ``python -m fbspost.cli compensate`` in its own tree, and
compares the written programs and the JSON reports (less their wall-clock fields and file paths)
byte for byte. A revision's outputs are cached under ``bench/.identical/<commit>``, so a second
run only recomputes the working tree's. ``--quick`` leaves out the two long prints. Exit status
0 when every output is identical, 1 otherwise (the differing files named, with their first
differing line).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CACHE = ROOT / "bench" / ".identical"
LONG = {"gear-marlin2.gcode", "blob-reprap-relative-e.gcode"}
# the report's fields that measure the computer or name the files (a worktree's own paths), not what was written
NOT_COMPARED = {"compute_time_s", "stage_time_s", "input", "output"}


@dataclass(frozen=True)
class Job:
    """One program with its machine profile and options; ``name`` keys its outputs."""
    program: Path
    machine: str
    options: tuple[str, ...] = ()

    @property
    def name(self) -> str:
        tag = "".join(self.options).replace("-", "")
        return f"{self.program.stem}.{self.machine}{'.' + tag if tag else ''}"


def corpus_dir() -> Path:
    return Path(os.environ.get("FBSPOST_CORPUS", ROOT.parent / "shared" / "corpus"))


def jobs(quick: bool) -> list[Job]:
    """The programs of tests/data, samples and the shared corpus (each distinct content once)."""
    found: list[Job] = []
    seen: set[str] = set()
    printers = sorted((ROOT / "tests" / "data").glob("*.gcode"))
    corpus = corpus_dir()
    printers += sorted(corpus.glob("*.gcode")) if corpus.is_dir() else []
    for path in printers:
        digest = hashlib.sha256(path.read_bytes()).hexdigest()
        if digest in seen or (quick and path.name in LONG):
            continue
        seen.add(digest)
        found.append(Job(path, "bedslinger-example"))
    found.append(Job(ROOT / "tests" / "data" / "tube-marlin2.gcode", "bedslinger-example", ("--format", "g5")))
    for path in sorted((ROOT / "samples").glob("*.gcode")):
        found.append(Job(path, "patent-xy-stage"))
        found.append(Job(path, "patent-xy-stage", ("--format", "g5")))
    return found


def compensate(tree: Path, job: Job, out_dir: Path) -> None:
    """``job`` compensated by the fbspost of ``tree`` into out_dir/NAME.gcode and NAME.json."""
    out = out_dir / f"{job.name}.gcode"
    report = out_dir / f"{job.name}.json"
    command = [sys.executable, "-m", "fbspost.cli", "compensate", str(job.program), "-o", str(out),
               "-m", f"machines/{job.machine}.toml", "--report", str(report), *job.options]
    env = dict(os.environ, PYTHONPATH=str(tree))
    done = subprocess.run(command, cwd=tree, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        out.write_text(f"exit status {done.returncode}\n{done.stderr}")
        return
    fields = json.loads(report.read_text())
    report.write_text(json.dumps({k: v for k, v in fields.items() if k not in NOT_COMPARED}, indent=1) + "\n")


def run_all(tree: Path, todo: list[Job], out_dir: Path, workers: int) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    missing = [job for job in todo if not (out_dir / f"{job.name}.json").exists()
               and not (out_dir / f"{job.name}.gcode").exists()]
    with ThreadPoolExecutor(workers) as pool:
        list(pool.map(lambda job: compensate(tree, job, out_dir), missing))


def _compared(report: Path) -> dict | None:
    """A report's fields less NOT_COMPARED (a cache may be older than NOT_COMPARED); None if not JSON."""
    try:
        return {k: v for k, v in json.loads(report.read_text()).items() if k not in NOT_COMPARED}
    except ValueError:
        return None


def first_difference(a: Path, b: Path) -> str:
    """'identical', or where ``a`` and ``b`` first differ (line number and both lines)."""
    if not b.exists():
        return "missing in the working tree"
    if a.read_bytes() == b.read_bytes() or (a.suffix == ".json" and None is not _compared(a) == _compared(b)):
        return "identical"
    for number, (left, right) in enumerate(zip(a.open("rb"), b.open("rb"), strict=True), start=1):
        if left != right:
            return f"line {number}: {left[:80]!r} != {right[:80]!r}"
    return "one is a prefix of the other"


def commit_of(rev: str) -> str:
    done = subprocess.run(["git", "rev-parse", rev], cwd=ROOT, check=True, capture_output=True, text=True)
    return done.stdout.strip()


def revision_outputs(commit: str, todo: list[Job], workers: int) -> Path:
    """The outputs of ``commit``'s code (cached by commit)."""
    out_dir = CACHE / commit
    with tempfile.TemporaryDirectory() as tmp:
        archive = subprocess.run(["git", "archive", commit], cwd=ROOT, check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", tmp], input=archive, check=True)
        run_all(Path(tmp), todo, out_dir, workers)
    return out_dir


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--base", default="main", help="the revision to compare with (default: main)")
    parser.add_argument("--head", help="a revision to compare instead of the working tree (its outputs cached too)")
    parser.add_argument("--quick", action="store_true", help="leave out the two long prints")
    parser.add_argument("--jobs", type=int, default=2, help="programs compensated at once")
    args = parser.parse_args()
    todo = jobs(args.quick)
    # (resolved now: a branch may move while the outputs are computed)
    base_commit, head_commit = commit_of(args.base), args.head and commit_of(args.head)
    print(f"base {args.base} = {base_commit}; head {args.head or 'the working tree'} = {head_commit or '-'}")
    base = revision_outputs(base_commit, todo, args.jobs)
    with tempfile.TemporaryDirectory() as tmp:
        if head_commit:
            head = revision_outputs(head_commit, todo, args.jobs)
        else:
            head = Path(tmp)
            run_all(ROOT, todo, head, args.jobs)
        verdicts = {job.name + ext: first_difference(base / (job.name + ext), head / (job.name + ext))
                    for job in todo for ext in (".gcode", ".json")}
    for name, verdict in verdicts.items():
        print(f"{name:60} {verdict}")
    differing = [name for name, verdict in verdicts.items() if verdict != "identical"]
    print(f"{len(verdicts) - len(differing)} of {len(verdicts)} outputs of {head_commit or 'the working tree'} "
          f"identical to {base_commit}'s" + (f"; differing: {' '.join(differing)}" if differing else ""))
    return 1 if differing else 0


if __name__ == "__main__":
    sys.exit(main())
