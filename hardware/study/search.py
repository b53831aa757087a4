"""NSGA-II over ``--space`` ranges (Optuna's sampler, its journal storage for resume), each trial
run on the Dask cluster as soon as a worker is free.

Optuna asks for one parameter set at a time and is told the front objectives (minimised); an
unsafe trial is told as infeasible (NSGA-II's constraint), one without figures as failed, so
neither steers the search towards itself. The study's journal lives beside the trial cache,
named by the hash of what decides its trials: a rerun of the same command resumes it.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from hapticloud.core.studies.trade.evaluate import TrialResult, TrialSpec, shipped_default
from hapticloud.core.studies.trade.front import FRONT_OBJECTIVES, LOOP_FRONT_OBJECTIVE
from hapticloud.core.studies.trade.knobs import SearchRange, is_closed_loop

from .cache import TrialCache, code_version
from .cluster import worker_count
from .runner import Outcome, run_trial

SIGNIFICANT_DIGITS = 4  #: searched floats are rounded so presets read as chosen numbers


def _round(value: float) -> float:
    if value == 0.0:
        return 0.0
    digits = SIGNIFICANT_DIGITS - 1 - math.floor(math.log10(abs(value)))
    return round(value, digits)


def _objective_names(space: Sequence[SearchRange]) -> tuple[str, ...]:
    loop = any(is_closed_loop(r.key) for r in space)
    return (*FRONT_OBJECTIVES, LOOP_FRONT_OBJECTIVE) if loop else FRONT_OBJECTIVES


def study_name(
    space: Sequence[SearchRange], template: TrialSpec, seed: int, population: int
) -> str:
    text = json.dumps(
        {
            "space": [dataclasses.astuple(r) for r in space],
            "spec": template.to_json(),
            "seed": seed,
            "population": population,
            "code": code_version(),
        },
        sort_keys=True,
    )
    return "trade-" + hashlib.sha256(text.encode()).hexdigest()[:16]


def _default_in_space(space: Sequence[SearchRange]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for r in space:
        out[r.key] = min(max(float(shipped_default(r.key)), r.lo), r.hi)
    return out


def nsga2(
    client: Any,
    space: Sequence[SearchRange],
    template: TrialSpec,
    n_trials: int,
    cache: TrialCache,
    *,
    journal: Path | None,
    resume: bool = True,
    seed: int = 0,
    population: int = 16,
    on_done: Callable[[int, TrialResult], None] | None = None,
) -> Outcome:
    """Run the search until ``n_trials`` trials have finished (resumed ones count)."""
    import optuna
    from distributed import as_completed
    from optuna.samplers import NSGAIISampler
    from optuna.trial import TrialState

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    names = _objective_names(space)
    storage: Any = None
    if journal is not None:
        from optuna.storages import JournalStorage
        from optuna.storages.journal import JournalFileBackend

        journal.parent.mkdir(parents=True, exist_ok=True)
        storage = JournalStorage(JournalFileBackend(str(journal)))
    name = study_name(space, template, seed, population)
    if storage is not None and not resume:
        try:
            optuna.delete_study(study_name=name, storage=storage)
        except KeyError:
            pass
    sampler = NSGAIISampler(population_size=population, seed=seed)
    study = optuna.create_study(
        study_name=name,
        storage=storage,
        sampler=sampler,
        directions=["minimize"] * len(names),
        load_if_exists=True,
    )
    outcome = Outcome([])
    for old in study.get_trials(deepcopy=False):
        if old.state == TrialState.RUNNING:  # a run stopped by Ctrl-C: measured again
            study.tell(old.number, state=TrialState.FAIL)
        elif "result" in old.user_attrs:
            outcome.results.append(TrialResult.from_json(old.user_attrs["result"], cached=True))
            outcome.cached += 1
            if on_done is not None:
                on_done(len(outcome.results) - 1, outcome.results[-1])
    if not study.trials:
        study.enqueue_trial(_default_in_space(space))

    def ask() -> tuple[Any, TrialSpec]:
        trial = study.ask()
        params: dict[str, Any] = {}
        for r in space:
            if r.integer:
                params[r.key] = trial.suggest_int(r.key, int(r.lo), int(r.hi), log=r.log)
            else:
                params[r.key] = _round(trial.suggest_float(r.key, r.lo, r.hi, log=r.log))
        return trial, dataclasses.replace(template, params=params)

    def tell(trial: Any, result: TrialResult) -> None:
        values = [float(result.objectives.get(n, math.nan)) for n in names]
        trial.set_user_attr("result", result.to_json())
        trial.set_constraint("unsafe", 1.0 if result.unsafe else -1.0)  # > 0: infeasible
        if all(math.isfinite(v) for v in values):
            study.tell(trial, values)
        else:
            study.tell(trial, state=TrialState.FAIL)
        outcome.results.append(result)
        if on_done is not None:
            on_done(len(outcome.results) - 1, result)

    in_flight: dict[Any, tuple[Any, TrialSpec]] = {}
    slots = worker_count(client) + 1
    stream = as_completed([])

    def fill() -> None:
        while len(outcome.results) + len(in_flight) < n_trials and len(in_flight) < slots:
            trial, spec = ask()
            hit = cache.get(spec)
            if hit is not None:
                outcome.cached += 1
                tell(trial, dataclasses.replace(hit, params=dict(spec.params)))
                continue
            future = client.submit(run_trial, spec, pure=False)
            in_flight[future] = (trial, spec)
            stream.add(future)

    try:
        fill()
        for future in stream:
            trial, spec = in_flight.pop(future)
            result = dataclasses.replace(future.result(), params=dict(spec.params))
            cache.put(spec, result)
            outcome.measured += 1
            tell(trial, result)
            fill()
    except KeyboardInterrupt:
        outcome.interrupted = True
        client.cancel(list(in_flight))
        for trial, _ in in_flight.values():
            study.tell(trial, state=TrialState.FAIL)
    return outcome


__all__ = ["SIGNIFICANT_DIGITS", "nsga2", "study_name"]
