"""The ``tdcr`` command line.  Bad input exits with code 2 and a message on stderr."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
from pathlib import Path

from tdcr.robot.design_space import DEFAULT_POINTS, MAX_TENDONS


class UsageError(Exception):
    """Bad input from the user: reported on stderr with exit code 2."""


def _at_least(minimum: float, kind: type = int):
    """An argparse type: a number of ``kind`` that is finite and at least ``minimum`` (else exit 2)."""
    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a{'n integer' if kind is int else ' number'}: {text!r}") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be at least {minimum}, got {text}")
        return value

    return parse


def _positive_seconds(text: str) -> float:
    """An argparse type: a time budget, s, finite and above 0."""
    value = _at_least(0.0, float)(text)
    if value == 0.0:
        raise argparse.ArgumentTypeError("must be above 0 s")
    return value


def _output_file(text: str) -> str:
    """An argparse type: a file the command can write at its end, checked before any work is done."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a directory")
    folder = path.parent
    if not folder.is_dir():
        raise argparse.ArgumentTypeError(f"no folder {folder} to write {path.name} in")
    if not os.access(folder, os.W_OK) or (path.exists() and not os.access(path, os.W_OK)):
        raise argparse.ArgumentTypeError(f"cannot write {text} (permission denied)")
    return text


def _output_file_or_stdout(text: str) -> str:
    """An argparse type: ``-`` (standard output) or an :func:`_output_file`."""
    return text if text == "-" else _output_file(text)


def _read_text(path: str) -> str:
    try:
        return sys.stdin.read() if path == "-" else Path(path).read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise UsageError(f"cannot read {path}: {getattr(exc, 'strerror', None) or exc}") from None


def _invalid(path: str, exc) -> UsageError:
    """A :class:`tdcr.api.validation.InvalidRequest` as a usage error, one problem per line."""
    from tdcr.api.validation import format_location

    lines = [f"{format_location(p.loc) or 'request'}: {p.msg}" for p in exc.problems]
    return UsageError(f"{path}: invalid request:\n  " + "\n  ".join(lines))


def _cmd_solve(args) -> int:
    from tdcr.api.schemas import RESPONSE_FORMAT_VERSION
    from tdcr.api.validation import InvalidRequest, validate_json
    from tdcr.physics.exact import solve_request

    try:  # a request, or a robot file (its design): the service's one validation path
        request = validate_json(_read_text(args.request), target="solver", limits=_unlimited())
    except InvalidRequest as exc:
        raise _invalid(args.request, exc) from None
    json.dump({"format_version": RESPONSE_FORMAT_VERSION, "results": solve_request(request).results()}, sys.stdout)
    sys.stdout.write("\n")
    return 0


def _robot_and_recording(robot_path: str, csv_path: str, *, measured: bool | None):
    from tdcr.robot.real import RobotFileError, load_robot, read_recording

    try:
        robot = load_robot(robot_path)
        return robot, read_recording(csv_path, robot, measured=measured)
    except RobotFileError as exc:
        raise UsageError(str(exc)) from None


def _cmd_replay(args) -> int:
    import time

    from tdcr.physics.replay import replay, write_predictions
    from tdcr.search.fit import errors, starts_crept

    robot, recording = _robot_and_recording(args.robot, args.commands, measured=None)  # scored where measured
    note = starts_crept(robot, recording.time)
    if note and not args.quiet:
        print(f"note: {note}", file=sys.stderr)
    # the first row alone first: a process's first replay loads the compiled kernel (about 0.5 s,
    # more than a few hundred rows take), which the rate would otherwise carry
    start = time.perf_counter()
    replay(robot, recording.commands[:1], workers=args.workers)
    startup = time.perf_counter() - start
    start = time.perf_counter()
    answer = replay(robot, recording.commands, time=recording.time, workers=args.workers, progress=not args.quiet)
    seconds = time.perf_counter() - start
    write_predictions(args.out, robot, recording, answer)
    n = len(recording.time)
    summary = {"rows": n, "seconds": seconds, "rows_per_second": n / seconds if seconds else None,
               "startup_seconds": startup, "not_converged": int((~answer.converged).sum()), "out": args.out}
    if all(c in recording.header for c in robot.measurement.columns):
        summary["errors"] = errors(answer, recording).as_dict()
    if note:
        summary["note"] = note
    json.dump(summary, sys.stdout, indent=None if args.quiet else 2)
    sys.stdout.write("\n")
    return 0


def _cmd_fit(args) -> int:
    from tdcr.search.fit import check_f_scale, check_groups, fit, parse_prior, plot

    groups = None if args.fit is None else tuple(g.strip() for g in args.fit.split(",") if g.strip())
    try:
        prior = parse_prior(args.prior)
    except ValueError as exc:
        raise UsageError(f"--prior: {exc}") from None
    problem = check_f_scale(args.f_scale)
    if problem:
        raise UsageError(f"--f-scale: {problem}")
    robot, train = _robot_and_recording(args.robot, args.train, measured=True)
    problem = None if groups is None else check_groups(groups, robot)
    if problem:
        raise UsageError(f"--fit: {problem}")
    validate = None if args.validate is None else _robot_and_recording(args.robot, args.validate, measured=True)[1]
    if not train.has_measurement.any():
        raise UsageError(f"{args.train}: no row has a measurement ({', '.join(robot.measurement.columns)})")
    result = fit(robot, train, validate=validate, groups=groups, max_iterations=args.max_iterations,
                 budget=args.budget, progress=not args.quiet, workers=args.workers, loss=args.loss,
                 f_scale=args.f_scale, prior=prior)
    result.robot.save(args.out)
    if args.plot:
        plot(result, train, validate, args.plot)
    report = result.report() | {"out": args.out}
    json.dump(report, sys.stdout, indent=None if args.quiet else 2)
    sys.stdout.write("\n")
    return 0


def _cmd_inverse(args) -> int:

    from tdcr.api.schemas import EXACT_MODEL
    from tdcr.api.validation import InvalidRequest, validate_inverse
    from tdcr.search.inverse import answer, answer_exact, finish, model_forward, model_tip_pose
    from tdcr.surrogates.runtime import ManifestError, Surrogate

    try:
        problem = validate_inverse(_read_text(args.request))
    except InvalidRequest as exc:
        raise _invalid(args.request, exc) from None
    if problem.model == EXACT_MODEL:
        results = answer_exact(problem)
    else:
        try:
            model = Surrogate.load(args.models_dir, problem.model)
        except ManifestError as exc:
            raise UsageError(f"{args.models_dir}: {exc}") from None

        tip_pose = model_tip_pose(model.predict, check=False)  # the differences may leave the bounds
        results = finish(problem, answer(problem, model_forward(problem.design, tip_pose)))
    json.dump({"model": problem.model, "results": results}, sys.stdout)
    sys.stdout.write("\n")
    return 0


def _cmd_generate(args) -> int:
    from tdcr.robot.design_space import LoadSpace
    from training.dataset import DatasetMismatch, GenerateConfig, generate

    if args.n < 1 or args.shard_size < 1 or args.points < 2:
        raise UsageError("--n and --shard-size must be >= 1 and --points >= 2")
    try:
        density = None if args.density is None else tuple(float(v) for v in args.density.split(","))
        if density is not None and len(density) != 2:
            raise ValueError(f"--density: LOW,HIGH in kg/m^3, got {args.density!r}")
        loads = LoadSpace(gravity=args.gravity, gravity_magnitude=args.gravity_magnitude, density=density,
                          tip_force=args.tip_force, tip_moment=args.tip_moment, tip_fraction=args.tip_fraction,
                          unloaded_fraction=args.unloaded_fraction)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if args.segments < 1 or args.tendons_per_segment < 1 or args.segments * args.tendons_per_segment > MAX_TENDONS:
        raise UsageError(f"--segments and --tendons-per-segment must be >= 1, at most {MAX_TENDONS} tendons in all")
    cfg = GenerateConfig(n=args.n, seed=args.seed, points=args.points, shard_size=args.shard_size, loads=loads,
                         segments=args.segments, tendons_per_segment=args.tendons_per_segment)
    try:
        meta = generate(args.out, cfg, workers=args.workers, scheduler=args.scheduler, progress=not args.quiet)
    except DatasetMismatch as exc:
        raise UsageError(str(exc)) from None
    print(json.dumps({k: meta[k] for k in ("n", "converged", "not_converged", "convergence_rate", "status_counts",
                                           "n_train", "n_test", "last_run")}))
    return 0


def _model_names(names: list[str] | None) -> list[str]:
    from training.operators.models import REGISTRY

    names = names or list(REGISTRY)
    unknown = [n for n in names if n not in REGISTRY]
    if unknown:
        raise UsageError(f"unknown model(s) {unknown}; known: {sorted(REGISTRY)}")
    return names


def _cmd_train(args) -> int:
    from training.operators.train import PRESETS, make_config, train

    _model_names([args.model])
    if args.preset not in PRESETS:
        raise UsageError(f"unknown preset {args.preset!r}; known: {sorted(PRESETS)}")
    if not (Path(args.data) / "metadata.json").exists():
        raise UsageError(f"{args.data} is not a dataset (no metadata.json); run `tdcr generate` first")
    hyper = json.loads(args.hyperparameters) if args.hyperparameters else {}
    cfg = make_config(args.model, args.preset, epochs=args.epochs, batch_size=args.batch_size, seed=args.seed,
                      dropout=args.dropout, n_train=args.n_train, time_budget_min=args.minutes,
                      patience=args.patience, loss=args.loss,
                      hyperparameters=hyper)
    try:
        summary = train(cfg, args.data, args.out or f"runs/{args.model}", progress=not args.quiet)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    print(json.dumps(summary))
    return 0


def _cmd_export(args) -> int:
    from tdcr.robot.design_space import LoadSpace
    from training.operators.export import export_run

    meta_path = Path(args.data) / "metadata.json" if args.data else None
    meta = None
    if meta_path is not None and meta_path.exists():
        full = json.loads(meta_path.read_text())
        meta = {k: full[k] for k in ("n", "seed", "n_train", "n_test", "points")}
        if full.get("loads") and not LoadSpace.from_record(full["loads"]).is_zero():
            meta["loads"] = full["loads"]  # the load space (a loaded operator's load_ranges)
        meta["split_seed"] = full["seed"] + 1  # training.dataset.split_indices: its first n_test are the test set
    for run in args.runs:
        if not (Path(run) / "model.pt").exists():
            raise UsageError(f"{run}: no model.pt (train it first)")
        entry = export_run(run, args.models_dir, dataset_meta=meta)
        print(f"exported {entry['name']} -> {Path(args.models_dir) / entry['file']} (sha256 {entry['sha256'][:12]})")
    return 0


def _cmd_evaluate(args) -> int:
    from training import dataset
    from training.operators.evaluate import (
        LOADED_REFERENCE,
        evaluate,
        evaluate_ood,
        format_ood,
        format_table,
        held_out,
        metrics_key,
        row_label,
    )
    from training.operators.export import update_manifest

    manifest_path = Path(args.models_dir) / "manifest.json"
    if not manifest_path.exists():
        raise UsageError(f"no manifest at {manifest_path}")
    manifest = json.loads(manifest_path.read_text())
    names = args.models or sorted(manifest["models"])
    missing = [n for n in names if n not in manifest["models"]]
    if missing:
        raise UsageError(f"not in the manifest: {missing}")
    try:
        test = dataset.load(args.data, "test")
    except (OSError, ValueError, KeyError) as exc:
        raise UsageError(f"{args.data}: not a dataset from `tdcr generate` ({exc.__class__.__name__})") from None
    keep, left_out, unknown = held_out(test["features"], {n: manifest["models"][n] for n in names})
    for name, count in left_out.items():
        if count:
            print(f"left out {count} of {len(keep)} test designs: in the training set of {name}", file=sys.stderr)
    if unknown:
        print(f"cannot tell which designs {unknown} were trained on (no dataset record in the manifest; "
              "`tdcr export --data` writes it): their test designs are all kept", file=sys.stderr)
    if not keep.any():
        raise UsageError(f"every test design of {args.data} is in a model's training set: generate another "
                         "dataset (e.g. another --seed) to evaluate on")
    results = evaluate(args.models_dir, args.data, names, keep=keep, exact_designs=args.exact_designs)
    loaded_data = LOADED_REFERENCE in results
    ood = evaluate_ood(args.models_dir, names, n=args.ood) if args.ood else None
    print(format_table(results))
    if ood is not None:
        print(f"\nout of distribution (mean relative l2, {args.ood} designs per bin):\n")
        print(format_ood(ood))
    if not args.update_manifest:
        print(f"\n{manifest_path} is unchanged (--update-manifest writes these metrics)", file=sys.stderr)
        return 0
    meta_path = Path(args.data) / "metadata.json"
    record = json.loads(meta_path.read_text()) if meta_path.exists() else {}
    evaluated_on = {k: record.get(k) for k in ("n", "seed", "n_test")} | {"n_held_out": int(keep.sum())}
    for name in names:
        entry = manifest["models"][name]
        key = metrics_key(entry, loaded_data)
        metrics = dict(entry.get("metrics") or {}) if key != "test_relative_l2" else {}
        metrics[key] = results[row_label(name, entry, loaded_data)]
        if key == "test_relative_l2" and loaded_data:
            metrics |= {"loaded_reference_relative_l2": results[LOADED_REFERENCE], "evaluated_on": evaluated_on}
        elif key == "test_relative_l2":
            metrics |= {"baseline_relative_l2": results["undeformed baseline"],
                        "linearized_reference_relative_l2": results["linearized reference"],
                        "evaluated_on": evaluated_on}
        else:
            metrics[key.replace("relative_l2", "evaluated_on")] = evaluated_on
        entry["metrics"] = metrics
        if ood is not None:
            entry["metrics"]["ood_mean_relative_l2"] = {label: row[name] for label, row in ood.items()}
        update_manifest(Path(args.models_dir), entry)
    print(f"\nwrote the metrics of {names} into {manifest_path}", file=sys.stderr)
    return 0


def _surrogate_named(models_dir: str, name: str):
    from tdcr.surrogates.runtime import ManifestError, Surrogate

    try:
        return Surrogate.load(models_dir, name)
    except ManifestError as exc:
        raise UsageError(f"{models_dir}: {exc}") from None


def _cmd_design(args) -> int:
    from tdcr.api.validation import InvalidRequest
    from tdcr.search.design import search, validate_task

    try:
        task = validate_task(_read_text(args.task))
    except InvalidRequest as exc:
        raise _invalid(args.task, exc) from None
    if args.budget_s is not None:
        if not args.budget_s > 0:
            raise UsageError("--budget-s must be > 0")
        task = dataclasses.replace(task, budget_s=args.budget_s)
    surrogate = None if args.inner == "exact" else _surrogate_named(args.models_dir, args.operator)
    result = search(task, surrogate=surrogate, inner=args.inner, progress=sys.stderr.isatty())
    json.dump(result.as_json(), sys.stdout)
    sys.stdout.write("\n")
    return 0


def _cmd_workspace(args) -> int:
    import time

    from tdcr.api.validation import InvalidRequest, validate_json
    from tdcr.search.design import plot_workspace, workspace

    if not 4 <= args.samples <= 1_000_000 or not 0 < args.tension_max <= 1000:
        raise UsageError("--samples must be in [4, 1000000] and --tension-max in (0, 1000] N")
    text = _read_text(args.design)
    try:
        body = json.loads(text)
    except ValueError:
        raise UsageError(f"{args.design}: not JSON") from None
    try:  # one design, as in a request (its tensions are ignored): the one validation path
        request = validate_json({"designs": [body]}, target="surrogate", limits=_unlimited())
    except InvalidRequest as exc:
        raise _invalid(args.design, exc) from None
    surrogate = None if args.model == "exact" else _surrogate_named(args.models_dir, args.model)
    started = time.perf_counter()
    space = workspace(request.features[0], samples=args.samples, tension_max=args.tension_max, seed=args.seed,
                      surrogate=surrogate)
    seconds = time.perf_counter() - started
    if args.png:
        plot_workspace(space, args.png)
    json.dump(space.as_json(seconds=seconds) | ({"png": args.png} if args.png else {}), sys.stdout)
    sys.stdout.write("\n")
    return 0


def _cmd_calibrate(args) -> int:
    from tdcr.surrogates.runtime import ManifestError, load_manifest
    from training.operators.calibrate import SCORES, TooFewDesigns, calibrate
    from training.operators.export import update_manifest

    try:
        manifest = load_manifest(args.models_dir)
    except ManifestError as exc:
        raise UsageError(str(exc)) from None
    names = args.models or sorted(n for n in manifest["models"] if n in SCORES)
    unknown = [n for n in names if n not in manifest["models"] or n not in SCORES]
    if unknown:
        raise UsageError(f"no manifest model or no measured score for {unknown}; calibrated: {sorted(SCORES)}")
    missing = sorted({c for n in names if (c := SCORES[n].companion) and c not in manifest["models"]})
    if missing:
        raise UsageError(f"the scores need the companion operators {missing}, not in the manifest")
    try:  # every record is computed before the manifest is written
        records = calibrate(args.models_dir, manifest, names, designs=args.designs, seed=args.seed)
    except TooFewDesigns as exc:  # the library names the count, the CLI its option
        raise UsageError(f"--designs: {exc}") from None
    for name, record in records.items():
        update_manifest(Path(args.models_dir), manifest["models"][name] | {"calibration": record})
        q = record["quantiles"]
        print(f"{name}: score {record['companion'] or record['score']}, {record['calibration_set']['converged']} "
              f"designs, quantiles {min(q):.3g}..{max(q):.3g}")
    return 0


def _cmd_study(args) -> int:
    import time

    from training import studies

    names = studies.STUDIES if args.name == "all" else (args.name,)
    if args.name != "all" and args.name not in studies.STUDIES:
        raise UsageError(f"unknown study {args.name!r}; known: {', '.join(studies.STUDIES)}, all")
    if args.budget not in studies.BUDGETS:
        raise UsageError(f"unknown budget {args.budget!r}; known: {', '.join(studies.BUDGETS)}")
    presets = tuple(args.presets.split(","))
    for preset in presets:
        if preset not in studies.PRESET_NAMES:
            raise UsageError(f"--presets: unknown preset {preset!r}; known: {', '.join(studies.PRESET_NAMES)}")
    if args.hours is not None and args.hours <= 0:
        raise UsageError(f"--hours: must be > 0, got {args.hours}")
    budget = studies.BUDGETS[args.budget]
    data = Path(args.data or f"data/study-{budget.name}")
    ctx = studies.Context(data=data, runs=Path(args.runs), out=Path(args.out), budget=budget, presets=presets,
                          models=tuple(_model_names(args.models or list(studies.MODEL_NAMES))), workers=args.workers,
                          stop_at=None if args.hours is None else time.time() + 3600.0 * args.hours,
                          models_dir=Path(args.models_dir),
                          progress=(lambda _msg: None) if args.quiet else (lambda msg: print(msg, flush=True)))
    for name in names:  # `all`: in the order of STUDIES, under one --hours deadline
        result = studies.run_study(name, ctx, plot_only=args.plot_only)
        table = result.pop("table")
        print(json.dumps({"study": name, "budget": budget.name, **result}), flush=True)
        if not args.quiet:
            print(table, flush=True)
    return 0


def _cmd_params(args) -> int:
    from training.operators.models import REGISTRY, build_model, count_parameters

    print("| model | paper | ours (paper inputs) | ours (tuned: physics inputs) |")
    print("|---|---:|---:|---:|")
    for name, (_, _, _, paper) in REGISTRY.items():
        ours = count_parameters(build_model(name))
        tuned = count_parameters(build_model(name, {"inputs": "physics"}))
        print(f"| {name} | {'-' if paper is None else f'{paper:,}'} | {ours:,} | {tuned:,} |")
    return 0


def _cmd_predict(args) -> int:
    from tdcr.api.checks import check_tolerance
    from tdcr.api.validation import InvalidRequest
    from tdcr.surrogates import engine
    from tdcr.surrogates.router import Router
    from tdcr.surrogates.runtime import ManifestError, Surrogate, best_model, load_manifest

    text = _read_text(args.request)
    try:
        request = engine.prepare_json(text, limits=_unlimited())
    except InvalidRequest as exc:
        raise _invalid(args.request, exc) from None
    if args.tolerance is not None:
        problems = check_tolerance(args.tolerance)
        if problems:
            raise UsageError(f"--tolerance: {problems[0].msg}")
        if request.jacobian:
            raise UsageError("--tolerance: the tip Jacobian is the operator's own: ask for it without a tolerance")
        request = dataclasses.replace(request, tolerance=args.tolerance)
    try:
        manifest = load_manifest(args.models_dir)
    except ManifestError as exc:
        raise UsageError(f"{args.models_dir}: {exc}") from None
    if request.model is not None and args.model is not None and request.model != args.model:
        raise UsageError(f"{args.request} names the model {request.model!r}, --model {args.model!r}: give one")
    pinned = args.model or request.model
    # the service's rule (service/state.py): a pinned model as asked; else the cheaper of the solver and
    # the default operator (designs with loads: the best loaded one), which meets the tolerance
    name = pinned or (request.n_loaded and best_model(manifest, loads=True)) or best_model(manifest, loads=None)
    if name not in manifest.get("models", {}):
        raise UsageError(f"unknown model {name!r}; available: {sorted(manifest.get('models', {}))}")
    try:
        model = Surrogate.load(args.models_dir, name, manifest=manifest)
    except ManifestError as exc:
        raise UsageError(f"{args.models_dir}: {exc}") from None
    guard = engine.local_guard(model)
    try:
        if pinned:
            prediction = engine.predict(model, request, model=name, guard_with=guard)
        else:
            costs = Router(model, model if model.takes_loads else None).costs
            prediction = engine.route(request, costs=costs, operator=engine.Operator(name, model, guard),
                                      exact=guard.exact)
    except InvalidRequest as exc:
        raise _invalid(args.request, exc) from None
    sys.stdout.buffer.write(engine.encode_json(prediction) + b"\n")
    return 0


def _unlimited():
    """Size limits of local commands: only the hard limit of points (the machine is the user's)."""
    from tdcr.api.validation import Limits

    return Limits(max_designs=sys.maxsize, max_design_points=sys.maxsize)


def _cmd_serve(args) -> int:
    import os

    import uvicorn

    from service.settings import Settings

    # the app factory (in each worker) reads its settings from the environment
    os.environ.setdefault("TDCR_GRPC_HOST", args.host)
    if args.grpc_port is not None:
        if not 0 <= args.grpc_port <= 65535:
            raise UsageError(f"--grpc-port must be 0 (off) to 65535, got {args.grpc_port}")
        os.environ["TDCR_GRPC_PORT"] = str(args.grpc_port)
    settings = Settings()
    if not (settings.models_dir / "manifest.json").exists():
        raise UsageError(f"no models at {settings.models_dir} (set TDCR_MODELS_DIR)")
    uvicorn.run("service.app:create_app", factory=True, host=args.host, port=args.port,
                workers=args.workers or settings.workers, log_level=args.log_level,
                http="service.http:GuardedHttpToolsProtocol", timeout_keep_alive=settings.keep_alive_s,
                limit_concurrency=settings.max_connections)
    return 0


def _cmd_loadtest(args) -> int:
    import asyncio

    from tdcr.clients.loadtest import format_rows, sweep

    def ints(text):
        try:
            values = [int(v) for v in text.split(",")]
        except ValueError:
            raise UsageError(f"expected comma-separated integers, got {text!r}") from None
        if any(v < 1 for v in values):
            raise UsageError("concurrency and batch sizes must be >= 1")
        return values

    if args.requests < 1 or args.seconds <= 0:
        raise UsageError("--requests must be >= 1 and --seconds > 0")
    rows, before, after = asyncio.run(sweep(
        args.url, concurrencies=ints(args.concurrency), batches=ints(args.batch), model=args.model,
        binary=args.binary, max_requests=args.requests, max_seconds=args.seconds, protocol=args.protocol,
        target=args.grpc_target, outputs=args.outputs))
    print(format_rows(rows, before, after))
    return 1 if any(r.errors for r in rows) else 0


def _cmd_openapi(args) -> int:
    from service.app import create_app

    document = create_app().openapi()
    text = json.dumps(document, indent=2, sort_keys=True) + "\n"
    if args.out == "-":
        sys.stdout.write(text)
    else:
        Path(args.out).write_text(text)
        print(f"wrote {args.out}: OpenAPI {document['openapi']}, {len(document['paths'])} paths, "
              f"{len(text):,} bytes", file=sys.stderr)
        from tdcr.robot.real import robot_schema

        robot = Path(args.out).with_name("robot.schema.json")  # the robot file's schema beside it
        robot.write_text(json.dumps(robot_schema(), indent=2, sort_keys=True) + "\n")
        print(f"wrote {robot}: the robot file's JSON Schema", file=sys.stderr)
    return 0


class FORMATTER(argparse.ArgumentDefaultsHelpFormatter):
    """Help of every command: each option's default shown, unless its help says it already (or there is none)."""

    def _get_help_string(self, action):
        text = action.help or ""
        unset = action.default is None or action.default is False or action.default == argparse.SUPPRESS
        if unset or "default" in text:
            return text
        return super()._get_help_string(action)


def build_parser() -> argparse.ArgumentParser:
    from tdcr.search.fit import BUDGET as FIT_BUDGET
    from tdcr.search.fit import DEFAULT_GROUPS as FIT_DEFAULT_GROUPS
    from tdcr.search.fit import DISPLACEMENT_ONLY as FIT_DISPLACEMENT_ONLY
    from tdcr.search.fit import F_SCALE as FIT_F_SCALE
    from tdcr.search.fit import GROUPS as FIT_GROUPS
    from tdcr.search.fit import LOSS as FIT_LOSS
    from tdcr.search.fit import LOSSES as FIT_LOSSES
    from tdcr.search.fit import MAX_ITERATIONS as FIT_MAX_ITERATIONS
    from tdcr.search.fit import PRIOR as FIT_PRIOR
    from tdcr.search.fit import format_prior
    from tdcr.surrogates.bounds import CALIBRATION_DESIGNS, CALIBRATION_SEED
    from tdcr.surrogates.runtime import DEFAULT_MODELS_DIR

    parser = argparse.ArgumentParser(prog="tdcr", description=__doc__.replace("``", ""),  # rst literals, as text
                                     formatter_class=FORMATTER)
    sub = parser.add_subparsers(dest="command", required=True)
    models_dir = {"default": str(DEFAULT_MODELS_DIR), "help": "directory with manifest.json and the ONNX models "
                                                              "(default: the shipped models)"}

    def command(name: str, help: str) -> argparse.ArgumentParser:
        # argparse %-formats a help string (not a description): a literal % in one must be doubled there
        return sub.add_parser(name, help=help.replace("%", "%%"), description=help, formatter_class=FORMATTER)

    p = command("solve", "exact equilibria of the designs in a request JSON (Cosserat solver)")
    p.add_argument("request", help="request JSON file, or - for stdin")
    p.set_defaults(func=_cmd_solve)

    p = command("replay", "a real robot's tip for every command row of a CSV (series-elastic tendons, friction)")
    p.add_argument("robot", help="robot file (JSON; see tdcr/robot/real.py and openapi/robot.schema.json)")
    p.add_argument("commands", help="CSV with the robot's time and actuation columns (in order of time)")
    p.add_argument("--out", required=True, type=_output_file,
                   help="predicted tips: CSV in the measurement's columns and unit")
    p.add_argument("--workers", type=_at_least(0), default=0, help="kernel threads (default 0: one per core)")
    p.add_argument("--quiet", action="store_true", help="no progress bar; the summary on one line")
    p.set_defaults(func=_cmd_replay)

    p = command("fit", "identify a real robot from motion-capture data (the 'design' extra: scipy, matplotlib)")
    p.add_argument("robot", help="robot file: the start of every parameter (with loads: fitted in rounds, "
                   "the first without them, each later one holding the loads' shift of the tips; "
                   "tdcr/search/fit.py)")
    p.add_argument("train", help="CSV of commands and measured tips to fit")
    p.add_argument("--validate", default=None, help="CSV only scored, by the fitted robot")
    p.add_argument("--out", required=True, type=_output_file,
                   help="the fitted robot file (replay, solve and the service take it)")
    p.add_argument("--plot", default=None, type=_output_file,
                   help="PNG of measured vs predicted tips and the error over time")
    p.add_argument("--fit", default=None,
                   help=f"comma-separated parameter groups, of {', '.join(FIT_GROUPS)} (tdcr/search/fit.py; "
                        f"default: {','.join(FIT_DEFAULT_GROUPS)}, without {', '.join(FIT_DISPLACEMENT_ONLY)} "
                        "for drives that command tensions)")
    p.add_argument("--max-iterations", type=_at_least(1), default=FIT_MAX_ITERATIONS,
                   help="least-squares iterations at most")
    p.add_argument("--budget", type=_positive_seconds, default=FIT_BUDGET,
                   help="seconds of search at most (then the best point); under loads the loaded replays come on top")
    p.add_argument("--prior", default=format_prior(FIT_PRIOR),
                   help="Gaussian prior around the robot file's values: GROUP=WIDTH[,GROUP=WIDTH...] in the "
                        "search's units (0.1 rad of a turn, 1 mm of a zero, 10 %% of E ...), or none")
    p.add_argument("--loss", choices=FIT_LOSSES, default=FIT_LOSS, help="loss on the point errors")
    p.add_argument("--f-scale", type=float, default=FIT_F_SCALE,
                   help="the loss's scale, mm: where soft_l1 turns linear; the prior's widths are against it")
    p.add_argument("--workers", type=_at_least(0), default=0, help="kernel threads (default 0: one per core)")
    p.add_argument("--quiet", action="store_true", help="no progress bar; the report on one line")
    p.set_defaults(func=_cmd_fit)

    p = command("inverse", "tensions that reach the targets of an inverse-kinematics request JSON")
    p.add_argument("request", help='{"design": ..., "targets": [{"position": [x, y, z]}, ...]} file, or - for stdin')
    p.add_argument("--models-dir", **models_dir)
    p.set_defaults(func=_cmd_inverse)

    p = command("generate", "generate a solver dataset of Table I designs (the 'data' extra for --scheduler)")
    p.add_argument("--n", type=int, required=True, help="number of designs")
    p.add_argument("--seed", type=int, default=0, help="seed of the designs, their loads and the train/test split")
    p.add_argument("--out", required=True, help="output directory (resumes if it exists)")
    p.add_argument("--points", type=int, default=DEFAULT_POINTS, help="equispaced arclengths per design")
    p.add_argument("--shard-size", type=int, default=1000, help="designs per shard file (the unit of resuming)")
    p.add_argument("--workers", type=int, default=None, help="local worker processes (default: all cores)")
    p.add_argument("--scheduler", default=None, help="address of a Dask distributed scheduler (default: local)")
    p.add_argument("--gravity", default="none",
                   help="none, sphere (|g| = --gravity-magnitude, uniform direction) or X,Y,Z in m/s^2")
    p.add_argument("--gravity-magnitude", type=float, default=9.81, help="|g| for --gravity sphere, m/s^2")
    p.add_argument("--density", default=None, help="LOW,HIGH backbone density range, kg/m^3 (with --gravity)")
    p.add_argument("--tip-force", type=float, default=0.0, help="largest tip force, N (uniform direction)")
    p.add_argument("--tip-moment", type=float, default=0.0, help="largest tip moment, N m (uniform direction)")
    p.add_argument("--tip-fraction", type=float, default=1.0, help="share of the designs with tip loads, in [0, 1]")
    p.add_argument("--unloaded-fraction", type=float, default=0.0,
                   help="share of the designs with no load at all (mixed data for a loaded operator), in [0, 1]")
    p.add_argument("--segments", type=int, default=1,
                   help="segments per robot: segment k's tendons end at (k + 1) L / segments (default 1)")
    p.add_argument("--tendons-per-segment", type=int, default=4,
                   help="tendons per segment, evenly spaced and staggered between segments (default 4)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_generate)

    p = command("train", "train one neural operator on a dataset (the 'train' extra: torch)")
    p.add_argument("--model", required=True, help="the operator: deeponet, deeponet_pose, fno or fno_pose")
    p.add_argument("--data", required=True, help="dataset directory from `tdcr generate`")
    p.add_argument("--out", default=None, help="run directory (default runs/MODEL); resumes if present")
    p.add_argument("--preset", default="tuned", help="paper (the paper's settings) or tuned (ours)")
    p.add_argument("--epochs", type=int, default=None, help="epochs (default: the preset's)")
    p.add_argument("--minutes", type=float, default=None, help="time budget; the schedule anneals within it")
    p.add_argument("--batch-size", type=int, default=None, help="designs per step (default: the preset's)")
    p.add_argument("--n-train", type=int, default=None, help="use only the first N training designs")
    p.add_argument("--dropout", type=float, default=None, help="dropout probability (default: the preset's)")
    p.add_argument("--seed", type=int, default=None, help="seed of initialisation, shuffles and dropout "
                                                          "(default: the preset's)")
    p.add_argument("--patience", type=int, default=None, help="stop after this many epochs without improvement")
    p.add_argument("--loss", choices=["mse", "relative", "relative_l2"], default=None,
                   help="mse: the paper's squared error (m^2); relative: mean squared relative l2; "
                        "relative_l2: mean relative l2 (the reported metric); default: the preset's")
    p.add_argument("--hyperparameters", default=None, help='JSON overrides, e.g. \'{"p": 50}\'')
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_train)

    p = command("export", "export trained runs to ONNX and update the manifest (the 'train' extra)")
    p.add_argument("runs", nargs="+", help="run directories holding model.pt")
    p.add_argument("--models-dir", **models_dir)
    p.add_argument("--data", default=None, help="dataset the runs were trained on (recorded in the manifest: "
                                                "seed, size and split, so that evaluations can leave it out)")
    p.set_defaults(func=_cmd_export)

    p = command("evaluate", "held-out relative l2 and tip error of exported models beside physics baselines "
                            "(the 'train' extra); the manifest changes only with --update-manifest")
    p.add_argument("--data", required=True, help="dataset directory from `tdcr generate` (its test split is used)")
    p.add_argument("--models-dir", **models_dir)
    p.add_argument("--models", nargs="*", default=None, help="models to evaluate (default: every manifest model)")
    p.add_argument("--ood", type=int, default=0, help="also the paper's OOD bins, with this many designs per bin")
    p.add_argument("--exact-designs", type=int, default=200,
                   help="on a dataset with loads: test designs on which the exact loaded solver is checked against "
                        "a 10x finer step (0: none)")
    p.add_argument("--update-manifest", action="store_true",
                   help="write these metrics into the manifest (the service picks its default model by them)")
    p.set_defaults(func=_cmd_evaluate)

    p = command("design", "search the design (E, r, L, offsets, pitches) that reaches a task's targets: CMA-ES "
                          "over an operator's batched inverse kinematics, proven by the exact solver (the 'design' "
                          "extra)")
    p.add_argument("task", help='{"targets": [{"position": [x, y, z]}, ...], "bounds"?, "fixed"?, "tension_max"?, '
                                '"tolerance"?, "objective"?, "seed"?, "budget_s"?} file, or - for stdin')
    p.add_argument("--operator", default="deeponet_pose", help="the operator of the inner inverse kinematics")
    p.add_argument("--inner", choices=["operator", "exact"], default="operator",
                   help="exact: the exact solver in the inner loop too (the baseline)")
    p.add_argument("--budget-s", type=float, default=None, help="overrides the task's budget_s")
    p.add_argument("--models-dir", **models_dir)
    p.set_defaults(func=_cmd_design)

    p = command("workspace", "Monte-Carlo reachable tips of one design over the tension box: JSON (samples, "
                             "hull volume, bounding box) and a PNG of three projections (the 'design' extra)")
    p.add_argument("design", help="one design as JSON (as in a request; its tensions are ignored), or - for stdin")
    p.add_argument("--samples", type=int, default=20_000, help="tension vectors, uniform in the box")
    p.add_argument("--tension-max", type=float, default=5.0, help="upper bound of every tension, N")
    p.add_argument("--model", default="exact", help="exact (the solver) or an operator's name")
    p.add_argument("--seed", type=int, default=0, help="seed of the sampled tensions")
    p.add_argument("--png", default=None, help="write the three projections here")
    p.add_argument("--models-dir", **models_dir)
    p.set_defaults(func=_cmd_workspace)

    p = command("calibrate", "calibrate the operators' 99 % error bounds on fresh exact solutions (split "
                             "conformal, Mondrian bins; the 'train' extra) and write them into the manifest")
    p.add_argument("--models-dir", **models_dir)
    p.add_argument("--models", nargs="*", default=None, help="operators (default: every one with a measured score)")
    p.add_argument("--designs", type=_at_least(1), default=CALIBRATION_DESIGNS,
                   help="calibration designs per group (load-free, loaded); too few for a finite bound in "
                        "every bending-angle bin exits 2")
    p.add_argument("--seed", type=int, default=CALIBRATION_SEED, help="seed of the calibration designs and loads")
    p.set_defaults(func=_cmd_calibrate)

    p = command("study", "run (or resume) one of the paper's studies; JSON lines + PNG under --out")
    p.add_argument("name", help="n-sweep, dropout, seeds, ood, timing, worst, or all (in that order)")
    p.add_argument("--budget", default="full", help="full (docs/report.md) or tiny (seconds; the tests')")
    p.add_argument("--data", default=None, help="dataset (generated if missing; default data/study-BUDGET)")
    p.add_argument("--runs", default="runs/study", help="training runs and checkpoints (resumable)")
    p.add_argument("--out", default="docs/study", help="where NAME.jsonl and NAME.png go")
    p.add_argument("--models-dir", **models_dir)
    p.add_argument("--presets", default="paper,tuned", help="comma-separated presets (paper, tuned)")
    p.add_argument("--models", nargs="*", default=None, help="operators (default: all four)")
    p.add_argument("--workers", type=int, default=1, help="training runs side by side (one thread each)")
    p.add_argument("--hours", type=float, default=None,
                   help="start no new epoch after this long; a later call resumes where this one stopped")
    p.add_argument("--plot-only", action="store_true", help="redraw NAME.png from NAME.jsonl")
    p.add_argument("--quiet", action="store_true", help="no tables")
    p.set_defaults(func=_cmd_study)

    p = command("params", "parameter counts of the four operators next to the paper's (the 'train' extra)")
    p.set_defaults(func=_cmd_params)

    p = command("predict", "surrogate shapes for a request JSON (onnxruntime only: the 'serve' extra)")
    p.add_argument("request", help="request JSON file, or - for stdin")
    p.add_argument("--model", default=None, help="the operator (default: the request's \"model\", else the "
                                                 "manifest's most accurate, as the service chooses)")
    p.add_argument("--models-dir", **models_dir)
    p.add_argument("--tolerance", type=float, default=None,
                   help="relative l2 error an answer may have: designs whose calibrated error bound exceeds it are "
                        "solved exactly (each result's source says which); overrides the request's \"tolerance\"")
    p.set_defaults(func=_cmd_predict)

    p = command("serve", "run the HTTP and gRPC service (the 'serve' extra; settings from TDCR_* variables)")
    p.add_argument("--host", default="127.0.0.1", help="address of both servers")
    p.add_argument("--port", type=int, default=8000, help="HTTP port")
    p.add_argument("--grpc-port", type=int, default=None,
                   help="gRPC (OIP v2) port; default TDCR_GRPC_PORT or 8001; 0: no gRPC server")
    p.add_argument("--workers", type=int, default=None, help="uvicorn worker processes (default: TDCR_WORKERS, 1)")
    p.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"],
                   help="uvicorn's log level")
    p.set_defaults(func=_cmd_serve)

    p = command("loadtest", "load-test a running service (bounded in requests and seconds)")
    p.add_argument("--url", default="http://127.0.0.1:8000", help="the service's HTTP address")
    p.add_argument("--concurrency", default="1,4,16,64", help="comma-separated client counts, one cell each")
    p.add_argument("--batch", default="1,32,1024", help="comma-separated designs per request, one cell each")
    p.add_argument("--model", default=None, help="the operator (default: the service's default)")
    p.add_argument("--binary", action="store_true", help=".npy requests and .npz answers instead of JSON")
    p.add_argument("--protocol", choices=["http", "v2", "grpc"], default="http",
                   help="http: /predict (JSON, or .npy with --binary); v2: the Open Inference Protocol over REST, "
                        "binary tensors; grpc: the same over gRPC, raw tensors")
    p.add_argument("--grpc-target", default=None, help="host:port of the gRPC server (default: --url's host, 8001)")
    p.add_argument("--outputs", default=None,
                   help="comma-separated outputs (binary, v2 and grpc), e.g. tendons; default: all shape arrays")
    p.add_argument("--requests", type=int, default=2000, help="at most this many requests per cell")
    p.add_argument("--seconds", type=float, default=10.0, help="at most this long per cell")
    p.set_defaults(func=_cmd_loadtest)

    p = command("openapi", "write the service's OpenAPI document")
    p.add_argument("--out", default="openapi/openapi.json", type=_output_file_or_stdout,
                   help="file to write, or - for stdout")
    p.set_defaults(func=_cmd_openapi)
    return parser


#: Third-party modules -> the extra that installs them.
EXTRAS = {"torch": "train", "onnx": "train", "onnxscript": "train", "matplotlib": "train",
          "fastapi": "serve", "uvicorn": "serve", "onnxruntime": "serve", "grpc": "serve", "httpx": "serve",
          "orjson": "serve", "prometheus_client": "serve", "pydantic_settings": "serve", "starlette": "serve",
          "dask": "data", "distributed": "data", "cma": "design", "scipy": "design", "crepes": "train",
          "sklearn": "train"}


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except UsageError as exc:
        print(f"tdcr {args.command}: {exc}", file=sys.stderr)
        return 2
    except ModuleNotFoundError as exc:  # a command of an extra that is not installed
        module = (exc.name or "").split(".")[0]
        if module not in EXTRAS:
            raise
        extra = EXTRAS[module]
        print(f"tdcr {args.command}: needs the '{extra}' extra (no module named {module!r}): "
              f"pip install -e '.[{extra}]', or bash scripts/test.sh, which installs every extra", file=sys.stderr)
        return 2
    except BrokenPipeError:  # e.g. `tdcr solve r.json | head`
        sys.stderr.close()
        return 0
    except KeyboardInterrupt:
        print(f"tdcr {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
