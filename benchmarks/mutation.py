"""Mutation testing of the safety code with mutmut; run by ``bash benchmarks/mutation.sh``.

mutmut names each mutant after the path of its file (``core/haptics/velocity.py`` would be the
module ``core.haptics.velocity``), but this project installs ``core/`` as ``hapticloud.core``: the
tests import ``hapticloud.core.haptics.velocity``, so mutmut would neither find the tests of a
mutant nor make them run it. This script therefore builds a tree laid out as installed::

    build/mutation/hapticloud/core/      copy of core/
    build/mutation/hapticloud/hardware/  copy of hardware/
    build/mutation/hapticloud/app/       copy of app/
    build/mutation/tests/                copy of tests/
    build/mutation/pyproject.toml        the project's, [tool.mutmut] as configured there

and runs ``mutmut run`` in it. mutmut copies ``hapticloud/`` to ``mutants/hapticloud/`` and puts
``mutants/`` first on ``sys.path``, so ``hapticloud.core`` (a sub-package of the namespace package
``hapticloud``) is imported from the mutated copy; ``hapticloud.assets``, not copied, still comes
from the editable install. Every run starts from an empty tree (mutmut would keep an old
survivor's result even after a test that kills it was added).

At the end it prints, per module and in total, how many mutants were generated, killed, survived
(including those no selected test reaches), timed out and excluded, and the score ``(killed +
timeout) / (generated - excluded)``; the last line of its output is that summary as one JSON line.
A surviving mutant is excluded only if a rule of ``benchmarks/mutation.toml`` (module, function,
original and mutated code, reason) matches it; a rule that matches nothing is an error, so the list
cannot go stale.

Exit code: 0 when every module scores at least ``--fail-under`` (90 %), 1 otherwise, 2 on bad
input or when mutmut itself fails.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import tomli_w

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("core", "hardware", "app")
EXCLUSIONS = ROOT / "benchmarks" / "mutation.toml"
DETECTED = ("killed", "timeout")


def tree_path(module: str) -> str:
    """``core/haptics/velocity.py`` -> ``hapticloud/core/haptics/velocity.py`` (either accepted)."""
    module = module.strip().removeprefix("./")
    if module.startswith("hapticloud/"):
        return module
    return f"hapticloud/{module}"


def repo_path(tree: str) -> str:
    return tree.removeprefix("hapticloud/")


@dataclass
class Rule:
    module: str
    function: str
    original: str
    mutated: str
    reason: str
    matched: list[str] = field(default_factory=list)

    def matches(self, module: str, function: str, removed: str, added: str) -> bool:
        return (
            self.module == module
            and self.function == function
            and self.original in removed
            and self.mutated in added
        )


def load_rules(path: Path) -> list[Rule]:
    data = tomllib.loads(path.read_text("utf-8")) if path.exists() else {}
    rules = []
    for i, entry in enumerate(data.get("exclude", [])):
        missing = {"module", "function", "original", "mutated", "reason"} - set(entry)
        if missing:
            raise SystemExit(f"mutation: {path.name}: exclude[{i}] lacks {sorted(missing)}")
        if not entry["reason"].strip():
            raise SystemExit(f"mutation: {path.name}: exclude[{i}] has no reason")
        rules.append(Rule(**{k: str(entry[k]) for k in Rule.__dataclass_fields__ if k in entry}))
    return rules


def build_tree(work: Path, only_mutate: list[str] | None) -> dict[str, Any]:
    """Lay out ``work`` as installed; returns the [tool.mutmut] table used there."""
    if work.exists():
        shutil.rmtree(work)
    (work / "hapticloud").mkdir(parents=True)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for top in PACKAGES:
        shutil.copytree(ROOT / top, work / "hapticloud" / top, ignore=ignore)
    shutil.copytree(ROOT / "tests", work / "tests", ignore=ignore)
    project = tomllib.loads((ROOT / "pyproject.toml").read_text("utf-8"))
    cfg = project.setdefault("tool", {}).setdefault("mutmut", {})
    if only_mutate is not None:
        cfg["only_mutate"] = only_mutate
    for module in cfg.get("only_mutate", []):
        if not (work / module).is_file():
            raise SystemExit(f"mutation: no such module: {repo_path(module)}")
    for arg in cfg.get("pytest_add_cli_args_test_selection", []):
        target = arg.removeprefix("--deselect=")
        if target.startswith("-"):
            continue
        file, _, test = target.partition("::")
        if not (work / file).is_file() or (
            test and f"def {test.partition('[')[0]}(" not in (work / file).read_text("utf-8")
        ):
            raise SystemExit(f"mutation: [tool.mutmut] names a missing test: {target}")
    (work / "pyproject.toml").write_text(tomli_w.dumps(project), "utf-8")
    return cfg


def function_name(mutant: str) -> str:
    """``hapticloud.core.x_foo__mutmut_3`` -> ``foo``; ``...xǁCǁm__mutmut_1`` -> ``C.m``."""
    mangled = mutant.partition("__mutmut_")[0].rpartition(".")[2]
    if mangled.startswith("x_"):
        return mangled[2:]
    return mangled[1:].replace("ǁ", ".")


def diff_lines(diff: str) -> tuple[str, str]:
    """The removed and the added code of a mutant's diff, each as one line of stripped text."""
    removed, added = [], []
    for line in diff.splitlines():
        if line.startswith(("---", "+++")):
            continue
        if line.startswith("-"):
            removed.append(line[1:].strip())
        elif line.startswith("+"):
            added.append(line[1:].strip())
    return " ".join(removed), " ".join(added)


def summarise(
    work: Path, modules: list[str], rules: list[Rule]
) -> tuple[dict[str, dict[str, Any]], list[dict[str, str]]]:
    """Per-module counts from mutmut's result files, survivors matched against the rules."""
    os.chdir(work)  # mutmut's helpers read mutants/ and pyproject.toml relative to the cwd
    from mutmut.mutation.diff_apply import get_diff_for_mutant
    from mutmut.stats import status_by_exit_code

    per_module: dict[str, dict[str, Any]] = {}
    undetected: list[dict[str, str]] = []
    for module in modules:
        meta = json.loads((work / "mutants" / f"{module}.meta").read_text("utf-8"))
        counts = dict.fromkeys(
            ("generated", "killed", "survived", "timeout", "no_tests", "excluded"), 0
        )
        for name, code in sorted(meta["exit_code_by_key"].items()):
            counts["generated"] += 1
            status = status_by_exit_code[code]
            if status in DETECTED:
                counts[status] += 1
                continue
            diff = get_diff_for_mutant(name, path=module)
            removed, added = diff_lines(diff)
            function = function_name(name)
            rule = next(
                (r for r in rules if r.matches(repo_path(module), function, removed, added)), None
            )
            if rule is not None:
                rule.matched.append(name)
                counts["excluded"] += 1
                continue
            counts["survived"] += 1
            if status == "no tests":
                counts["no_tests"] += 1
            undetected.append(
                {"module": repo_path(module), "mutant": name, "status": status, "diff": diff}
            )
        counted = counts["generated"] - counts["excluded"]
        detected = counts["killed"] + counts["timeout"]
        counts["score"] = round(100.0 * detected / counted, 1) if counted else 100.0
        per_module[repo_path(module)] = counts
    return per_module, undetected


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="bash benchmarks/mutation.sh", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument(
        "modules",
        nargs="*",
        metavar="MODULE",
        help="files to mutate, e.g. core/haptics/velocity.py (default: [tool.mutmut] only_mutate)",
    )
    parser.add_argument(
        "--jobs",
        type=int,
        default=int(os.environ.get("MUTATION_JOBS", "1")),
        help="mutants run at once (default 1, or $MUTATION_JOBS)",
    )
    parser.add_argument(
        "--workdir",
        type=Path,
        default=Path(os.environ.get("MUTATION_WORKDIR", ROOT / "build" / "mutation")),
        help="the tree mutmut runs in (emptied first; default build/mutation)",
    )
    parser.add_argument("--fail-under", type=float, default=90.0, help="per-module score, %%")
    parser.add_argument(
        "--report-only",
        action="store_true",
        help="summarise the last run in --workdir again (after editing the exclusions)",
    )
    args = parser.parse_args(argv)
    if args.jobs < 1:
        parser.error("--jobs must be >= 1")

    start = time.monotonic()
    work = args.workdir.resolve()
    only = [tree_path(m) for m in args.modules] if args.modules else None
    rules = load_rules(EXCLUSIONS)
    if args.report_only:
        if not (work / "mutants").is_dir():
            parser.error(f"--report-only: no run in {work}")
        cfg = tomllib.loads((work / "pyproject.toml").read_text("utf-8"))["tool"]["mutmut"]
    else:
        cfg = build_tree(work, only)
    modules = list(cfg.get("only_mutate", []))
    if not modules:
        print("mutation: nothing to mutate ([tool.mutmut] only_mutate is empty)", file=sys.stderr)
        return 2

    if not args.report_only:
        mutmut = Path(sys.executable).parent / "mutmut"
        log = work / "mutmut.log"
        print(f"mutation: {len(modules)} module(s), {args.jobs} job(s), log in {log}", flush=True)
        with log.open("w") as out:
            proc = subprocess.run(
                [str(mutmut), "run", "--max-children", str(args.jobs)],
                cwd=work,
                stdout=out,
                stderr=subprocess.STDOUT,
                env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"},
                check=False,
            )
        if proc.returncode != 0:
            print(log.read_text("utf-8", errors="replace")[-4000:], file=sys.stderr)
            print(f"mutation: mutmut failed (exit code {proc.returncode})", file=sys.stderr)
            return 2

    rules_here = [r for r in rules if tree_path(r.module) in modules]
    per_module, undetected = summarise(work, modules, rules_here)
    stale = [r for r in rules_here if not r.matched]

    for item in undetected:
        print(f"\n{item['status']}: {item['mutant']}\n{item['diff'].rstrip()}")
    for rule in rules_here:
        for name in rule.matched:
            print(f"excluded: {name}: {rule.reason}")
    for rule in stale:
        print(
            f"mutation: stale exclusion in {EXCLUSIONS.name} ({rule.module} {rule.function}: "
            f"{rule.original!r} -> {rule.mutated!r}): it matches no surviving mutant",
            file=sys.stderr,
        )
    total = {
        k: sum(m[k] for m in per_module.values())
        for k in ("generated", "killed", "survived", "timeout", "no_tests", "excluded")
    }
    counted = total["generated"] - total["excluded"]
    total["score"] = (
        round(100.0 * (total["killed"] + total["timeout"]) / counted, 1) if counted else 100.0
    )
    ok = all(m["score"] >= args.fail_under for m in per_module.values()) and not stale
    summary = {
        "modules": per_module,
        "total": total,
        "fail_under": args.fail_under,
        "ok": ok,
        "jobs": args.jobs,
        "wall_s": round(time.monotonic() - start, 1),
    }
    report = {**summary, "undetected": undetected}
    (work / "summary.json").write_text(json.dumps(report, indent=2) + "\n", "utf-8")
    print()
    for name, m in per_module.items():
        print(
            f"{name:42s} {m['generated']:4d} mutants  {m['killed']:4d} killed  "
            f"{m['survived']:3d} survived  {m['timeout']:2d} timeout  {m['excluded']:2d} excluded"
            f"  {m['score']:5.1f} %"
        )
    print(json.dumps(summary, separators=(",", ":")))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
