"""The default method on systems without a preset: certified share of the true ROA and time.

Usage: python bench/default_training.py [--cases vdp3,power,examples/X.toml,...]
       [--settings known,learned]
       [--seeds K | K1,K2,... | A-B] [--jobs N] [--out DIR]

Each case is run as a user would, with default settings: ``nlyap run SPEC
[--known-dynamics] --out DIR`` for a spec file, ``nlyap run NAME --preset default`` for a
catalogue system (its preset is not used). A case ``NAME@large`` runs the catalogue system
with default settings on its ``large`` preset's sets: ``--config`` with that preset's
``domain`` (the ball of radius ``outer`` when it has none), ``inner`` and ``eval_box``, the
sets on which the ``large`` presets' shares were measured; nothing else of the preset. A
case that is a spec file's path (``examples/X.toml``) runs that file as it is, its ``[run]``
table included.
``--seeds`` sets ``train.seed`` (a ``--config`` override), one run per seed: one training
trajectory is one sample, and a change of the training is real only if it moves the
spread over seeds, which is printed after the runs (median, smallest and largest share per
case and setting) when more than one seed is given. ``--jobs N`` runs N commands at once
(each single-threaded but for NumPy's BLAS outside the φ fit); the rows are printed in the
order of the commands.

Prints one Markdown row per run (status, the certified share of the simulated true ROA
within the domain; the share of that true ROA whose trajectories never leave the domain,
which bounds every certificate in it; wall seconds and the run's own CPU seconds) with the
command, the machine and its load average. On a machine shared with other jobs (or with
``--jobs``) a run's CPU seconds are close to the wall seconds it takes on an idle one,
while its wall seconds grow with the load. The peers' shares are LyZNet's published ones
on the same boxes."""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from seeds import parse_seeds

ROOT = Path(__file__).resolve().parents[1]

#: name: (what nlyap runs, the peer's share or None)
CASES = {
    "vdp3": ("examples/van_der_pol_mu3.toml", 85.2),
    "power": ("examples/two_machine_power.toml", 82.3),
    "khalil": ("examples/box_domain.toml", None),
    "van_der_pol": ("van_der_pol", None),
    "unicycle_path_following": ("unicycle_path_following", None),
    "inverted_pendulum": ("inverted_pendulum", None),
}
#: the ``large`` presets' shares (of the true ROA in their own sets), for NAME@large
LARGE_SHARES = {"van_der_pol": 95.8, "unicycle_path_following": 91.5,
                "inverted_pendulum": 93.3}


def large_sets(name: str) -> dict:
    """The config overrides that put the default method on the ``large`` preset's sets of
    catalogue system ``name``: its ``domain`` (or the ball of radius ``outer``), ``inner``
    and ``eval_box``, and (for learned dynamics) the box on which its φ is learned and
    bounded, ``dynamics.state_box``, which must hold the domain."""
    from nlyap_opt.workflow.configs import get_config

    large = get_config(name, "large").to_json()
    domain = large.get("domain") or {"type": "ball", "radius": large["outer"]}
    out = {"domain": domain, "inner": large["inner"], "eval_box": large["eval_box"]}
    box = (large.get("dynamics") or {}).get("state_box")
    if box is not None:
        out["dynamics"] = {"state_box": box}
    return out


def case(name: str) -> tuple[str, float | None, dict]:
    """What ``nlyap`` runs for case ``name``, the share to compare with and the overrides."""
    if name.endswith(".toml"):
        return name, None, {}
    if name.endswith("@large"):
        system = name[:-len("@large")]
        return system, LARGE_SHARES.get(system), large_sets(system)
    target, peer = CASES[name]
    return target, peer, {}


def _bad_case(name: str) -> str | None:
    """Why ``name`` is not a case (``None``: it is one)."""
    if name.endswith(".toml"):
        return None if (ROOT / name).is_file() or Path(name).is_file() else \
            f"--cases: no spec file {name!r}"
    if name.endswith("@large"):
        system = name[:-len("@large")]
        return None if system in LARGE_SHARES else (
            f"--cases: {name!r}: no large preset for {system!r}; NAME@large takes one of "
            f"{', '.join(LARGE_SHARES)}")
    return None if name in CASES else (
        f"--cases: unknown case {name!r}; use one of {', '.join(CASES)}, NAME@large "
        f"(NAME: {', '.join(LARGE_SHARES)}) or a spec file's path (examples/X.toml)")


def _machine() -> str:
    return (f"{platform.node()}: {platform.processor() or platform.machine()}, "
            f"{os.cpu_count()} CPUs, Python {platform.python_version()}")


def run_case(target: str, known: bool, out: Path, overrides: dict | None = None
             ) -> tuple[list[str], dict, float, float]:
    """``nlyap run`` of one case (``overrides``: a ``--config`` file written next to
    ``out``); returns the command, certificate.json, wall seconds and the CPU seconds (user
    + system) of that process alone (``os.wait4``: right when runs go side by side)."""
    cmd = [sys.executable, "-m", "nlyap_opt.interface.cli", "run", target, "--out", str(out)]
    if not target.endswith(".toml"):
        cmd += ["--preset", "default"]
    if known:
        cmd.append("--known-dynamics")
    if overrides:
        path = out.with_suffix(".config.json")
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(overrides))
        cmd += ["--config", str(path)]
    t = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)   # reaped: Popen must not wait
    seconds = time.perf_counter() - t
    cpu = usage.ru_utime + usage.ru_stime
    path = out / "certificate.json"
    cert = json.loads(path.read_text()) if path.exists() else {"status": "failed"}
    return cmd, cert, seconds, cpu


def stay_share(cert: dict) -> float | None:
    """The share of the simulated true ROA within D whose trajectories never leave D, under
    the run's controller (``certificate.json``'s ``true_roa_stays_in_domain``): no
    certificate in D can hold more (a certified set lies in D and is forward invariant).
    ``None`` when the run certified nothing or its true ROA was not simulated."""
    if cert.get("status") != "certified":
        return None
    return cert.get("true_roa_stays_in_domain")


def _runs(cases: list[str], settings: list[str], seeds: list[int | None]) -> list[tuple]:
    """(case, setting, seed, nlyap target, peer share, overrides) of every run, in order."""
    runs = []
    for name in cases:
        target, peer, overrides = case(name)
        for setting in settings:
            for seed in seeds:
                over = overrides if seed is None else {**overrides, "train": {"seed": seed}}
                runs.append((name, setting, seed, target, peer, over))
    return runs


def _row(run: tuple, base: Path, several: bool) -> tuple[str, float | None]:
    """Run one case; its Markdown row and its certified share (``None``: none)."""
    name, setting, seed, target, peer, overrides = run
    label = Path(name).stem if name.endswith(".toml") else name
    known = setting == "known"
    out = base / (f"{label}_{setting}" + (f"_seed{seed}" if several else ""))
    cmd, cert, sec, cpu = run_case(target, known, out, overrides)
    bound = stay_share(cert)
    share = cert.get("fraction_of_true_roa") if cert["status"] == "certified" else None
    command = "nlyap " + " ".join(cmd[3:5]) + (" --preset default" if "--preset" in cmd
                                                else "") + \
        (" --known-dynamics" if known else "") + \
        (f" --config {json.dumps(overrides)}" if overrides else "")
    row = (f"| {name} | {'true' if known else 'learned'} | {cert['status']} | "
           f"{'–' if share is None else f'{100 * share:.1f}'} | "
           f"{'–' if bound is None else f'{100 * bound:.1f}'} | "
           f"{'' if peer is None else peer} | {sec:.0f} | {cpu:.0f} | "
           f"{os.getloadavg()[1]:.1f} | `{command}` |")
    return row, share


def spread(shares: list[float | None]) -> str:
    """Median, smallest and largest certified share (in %) of a case's seeds, and how many
    seeds certified; a seed that certified nothing counts as 0 %."""
    got = [0.0 if s is None else 100 * s for s in shares]
    return (f"{statistics.median(got):.1f} | {min(got):.1f} | {max(got):.1f} | "
            f"{sum(s is not None for s in shares)}/{len(shares)}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="vdp3,power")
    ap.add_argument("--settings", default="known,learned")
    ap.add_argument("--seeds", default=None,
                    help="train.seed of the runs: K, K1,K2,... or A-B (default: the "
                         "configuration's seed)")
    ap.add_argument("--jobs", type=int, default=1, help="runs at once (default 1)")
    ap.add_argument("--out", default=None, help="keep the runs here (default: a temp dir)")
    args = ap.parse_args()
    cases, settings = args.cases.split(","), args.settings.split(",")
    for given, what in ((cases, "--cases"), (settings, "--settings")):
        twice = sorted({x for x in given if given.count(x) > 1})
        if twice:
            ap.error(f"{what}: {', '.join(twice)} given twice (their runs would share a "
                     "directory); give each once")
    for name in cases:
        bad = _bad_case(name)
        if bad:
            ap.error(bad)
    for setting in settings:
        if setting not in ("known", "learned"):
            ap.error(f"--settings: unknown setting {setting!r}; use known, learned or both "
                     "(comma-separated)")
    try:
        seeds = [None] if args.seeds is None else parse_seeds(args.seeds)
    except ValueError as err:
        ap.error(f"--seeds: {err}")
    if args.jobs < 1:
        ap.error(f"--jobs: {args.jobs} runs at once; give 1 or more")
    base = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="nlyap_default_"))
    print(f"machine: {_machine()}; load average {os.getloadavg()[0]:.1f} at the start; "
          f"{args.jobs} run(s) at once")
    print("| case | f | status | share % | stays in D % | peer % | wall s | CPU s | load | "
          "command |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    runs = _runs(cases, settings, seeds)
    shares: dict = {}
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        futures = [pool.submit(_row, r, base, len(seeds) > 1) for r in runs]
        for r, fut in zip(runs, futures):
            row, share = fut.result()
            shares.setdefault((r[0], r[1]), []).append(share)
            print(row, flush=True)
    if len(seeds) > 1:
        print(f"\nOver train.seed {args.seeds}:\n")
        print("| case | f | median share % | smallest % | largest % | certified |")
        print("|---|---|---|---|---|---|")
        for (name, setting), got in shares.items():
            print(f"| {name} | {'true' if setting == 'known' else 'learned'} | "
                  f"{spread(got)} |")


if __name__ == "__main__":
    main()
