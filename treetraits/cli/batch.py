"""`treetraits batch`: a season of recordings replayed in parallel on Dask distributed,
gathered into a season store (docs/season.md)."""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from pathlib import Path

from treetraits.errors import EXIT_DATA_LOSS, ConfigError
from treetraits.files import check_output_file


def register(commands: argparse._SubParsersAction) -> None:
    from treetraits.pipeline.methods import METHODS, TRAIT_METHODS

    batch = commands.add_parser(
        "batch",
        help="replay many recordings in parallel (Dask) into a season store",
        description=(
            "Replay every recording REC through the pipeline, one Dask task per recording, "
            "on a local cluster of --workers processes or on a running Dask scheduler "
            "(--scheduler tcp://HOST:8786), each into its own run directory, and gather "
            "their trees into the season store SEASON.sqlite, linking each tree across "
            "surveys (docs/season.md). A recording already in the season, processed by "
            "this software with the same config, is skipped (--force reprocesses it). A "
            "recording that fails is reported and the others go on."
        ),
    )
    batch.add_argument("recordings", nargs="+", type=Path, metavar="REC", help="recordings")
    batch.add_argument("--season", required=True, type=Path, help="season store (SQLite)")
    batch.add_argument(
        "--config",
        type=Path,
        help="config file (TOML) for every replay, as `treetraits replay --config`; the "
        "skip key covers it (default: the built-in defaults)",
    )
    batch.add_argument("--method", choices=METHODS, help="overrides pipeline.method")
    batch.add_argument("--traits", choices=TRAIT_METHODS, help="overrides traits.method")
    batch.add_argument(
        "--block",
        default="block",
        help="the block (field) these recordings surveyed: trees are linked across the "
        "surveys of one block (default 'block')",
    )
    batch.add_argument(
        "--workers",
        type=int,
        default=2,
        help="processes of the local Dask cluster, one replay each at a time (default 2; "
        "more than the machine's cores only slows each replay down)",
    )
    batch.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="a running Dask scheduler (tcp://HOST:8786) to submit to instead of a local "
        "cluster; its workers must have treetraits installed and see the recordings and "
        "--runs at the same paths",
    )
    batch.add_argument(
        "--scheduler-timeout",
        type=float,
        default=20.0,
        metavar="SECONDS",
        help="how long to wait for --scheduler to answer before giving up (default 20)",
    )
    batch.add_argument(
        "--runs",
        type=Path,
        help="where the run directories go, one per recording (default: SEASON.runs/ "
        "beside the season store)",
    )
    batch.add_argument(
        "--link-gate",
        type=float,
        default=None,
        metavar="M",
        help="metres within which two surveys' trees off the field map are one tree "
        "(default 1.2: under half the closest tree spacing)",
    )
    batch.add_argument(
        "--force",
        action="store_true",
        help="reprocess recordings already in the season with this software and config",
    )
    batch.add_argument(
        "--allow-damaged",
        action="store_true",
        help="exit 0 also when a recording was damaged (its readable part is in the season)",
    )
    batch.add_argument("--json", action="store_true", help="print the outcome as JSON")
    batch.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from treetraits.extras import require_extra

    require_extra("season", "treetraits batch")
    from tqdm import tqdm

    from treetraits.pipeline.linking import DEFAULT_LINK_GATE_M
    from treetraits.season import batch as b
    from treetraits.season.store import SeasonStore, Survey
    from treetraits.service.config import load_config, with_method
    from treetraits.service.outdir import output_lock

    if args.workers < 1:
        raise ConfigError(f"--workers must be at least 1, got {args.workers}")
    if not args.scheduler_timeout > 0:
        wait = args.scheduler_timeout
        raise ConfigError(f"--scheduler-timeout must be a positive number of seconds, got {wait}")
    gate = DEFAULT_LINK_GATE_M if args.link_gate is None else args.link_gate
    if not gate > 0:
        raise ConfigError(f"--link-gate must be a positive number of metres, got {gate}")
    check_output_file(args.season, "--season")  # written in place: it may exist
    config = with_method(load_config(args.config), args.method, args.traits)
    key = b.config_key(config)
    runs_dir = args.runs or args.season.with_name(args.season.name + ".runs")
    outcome = b.BatchOutcome()

    # One batch per season at a time: the client is the season's only writer.
    with (
        output_lock(args.season.resolve().parent, f".{args.season.name}.lock"),
        SeasonStore(args.season) as season,
    ):
        items = b.plan(args.recordings, season, args.block, key, runs_dir, args.force, outcome)
        for recording, error in outcome.failed.items():
            season.add_failure(recording, args.block, b.SOFTWARE, key, error, b.now_iso())
        if items:
            runs_dir.mkdir(parents=True, exist_ok=True)
            changed = False
            with (
                _client(args) as client,
                tqdm(total=len(items), unit="rec", desc="batch", disable=None) as bar,
            ):

                def on_result(item, result, error) -> None:
                    nonlocal changed
                    name = str(item.recording)
                    if result is not None and result.ok:
                        survey = Survey(
                            args.block,
                            name,
                            item.fingerprint,
                            result.t_start,
                            b.SOFTWARE,
                            key,
                            result.run_dir,
                            bool(result.summary.get("data_loss")),
                            result.summary,
                        )
                        season.add_survey(survey, b.trees_of(result), b.now_iso())
                        changed = True
                        outcome.processed.append(name)
                        if survey.data_loss:
                            outcome.damaged.append(name)
                    else:
                        error = error or (result.error if result else "unknown error")
                        outcome.failed[name] = error
                        season.add_failure(name, args.block, b.SOFTWARE, key, error, b.now_iso())
                        bar.write(f"treetraits: error: {name}: {error}", file=sys.stderr)
                    bar.update()

                try:
                    b.run_batch(items, client, config, on_result)
                finally:
                    # Also after Ctrl-C: the surveys committed so far are linked.
                    if changed:
                        season.relink(args.block, gate)
        trees = len(season.trees())

    for name in outcome.damaged:
        print(
            f"treetraits: warning: {name}: damaged or cut; its readable part is in the season",
            file=sys.stderr,
        )
    failed = bool(outcome.failed) or (bool(outcome.damaged) and not args.allow_damaged)
    status = EXIT_DATA_LOSS if failed else 0
    if args.json:
        print(json.dumps(dict(outcome.as_json(), season=str(args.season), trees=trees), indent=1))
        return status
    print(
        f"{len(outcome.processed)} processed, {len(outcome.skipped)} skipped (already in the "
        f"season), {len(outcome.failed)} failed; {trees} trees in {args.season}"
    )
    for name, error in outcome.failed.items():
        print(f"FAILED {name}: {error}")
    return status


@contextlib.contextmanager
def _client(args: argparse.Namespace):
    """A Dask client: on the scheduler given, else on a local cluster of processes (one
    thread each: the pipeline holds the GIL much of the time, and Open3D has threads of
    its own)."""
    from distributed import Client, LocalCluster

    from treetraits.errors import SourceError

    if args.scheduler:
        try:
            client = Client(args.scheduler, timeout=f"{args.scheduler_timeout}s")
        except (OSError, TimeoutError) as exc:
            raise SourceError(
                f"--scheduler {args.scheduler}: cannot connect ({exc}); is `dask scheduler` "
                "running there?"
            ) from None
        with client:
            yield client
        return
    with (
        LocalCluster(
            n_workers=args.workers,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            silence_logs=40,  # errors only: the tasks' failures are reported by the client
        ) as cluster,
        Client(cluster) as client,
    ):
        yield client
