"""Adapting a model to another sensor: the target's mIoU before and after, on simulated scenes.

One run simulates a labelled 64-beam source dataset (the `semantickitti` profile at 64 x 512) and
a 32-beam target sensor (a profile written here: +10 to -30 degrees, 32 x 512, one firing per
column, mounted 1.9 m high instead of 1.73 m, SemanticKITTI's label set), with a few labelled
target scans for training and held-out target sequences for testing. It trains a small source
network on the CPU (rangeret-cir, one block of width 64), checks it on held-out source scans, and
scores on the target's held-out scans (`rangeret predict --profile TARGET --label-map`, then
`rangeret evaluate`):

  a. the source network as it is;
  b. fine-tuned (`train --init-from`) on the source data adapted to the target (`rangeret adapt`
     with the mounting difference as `--sensor-offset`);
  c. fine-tuned on the few labelled target scans alone;
  d. fine-tuned on both: the adapted tree with the target scans linked in as extra sequences,
     repeated so that they make about half of it.

b, c and d take the same number of steps and recipe; every seed is fixed. Every step is a
subprocess of the `rangeret` command, logged to OUT/work/logs. Prints the mIoU and the IoU of the
main classes, writes OUT/adapt.json, OUT/adapt.png and `rangeret compare`'s OUT/compare.png.
The default run took 20 minutes on two CPU cores; `--quick` is a smoke run of about a minute.
Run by hand: `python benchmarks/bench_adapt.py [--out DIR] [--quick]`.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from _common import REPO

#: The classes whose IoU the table shows besides the mIoU.
MAIN_CLASSES = ("road", "sidewalk", "car", "building", "vegetation", "terrain")
#: The source: SemanticKITTI's sensor (1.73 m high), at 64 x 512.
SOURCE_PROFILE = "semantickitti"
SOURCE_SIZE = (64, 512)
SOURCE_MOUNT = 1.73
#: The target sensor: 32 beams over +10 to -30 degrees, 32 x 512, 1.9 m high.
TARGET = {"height": 32, "width": 512, "fov_up": 10.0, "fov_down": -30.0, "mount_height": 1.9}
#: The network: rangeret-cir cut to one block of width 64, so that it trains on two CPU cores.
NETWORK = ("rangeret-cir", ("layers=1", "dim=64"))
#: Fine-tuning recipe of b, c and d: OneCycle from 0.0003 to a peak of 0.003.
FINETUNE_LR = ("0.0003", "0.003")
VARIANTS = {
    "a": "source network as it is",
    "b": "fine-tuned on adapted source data",
    "c": "fine-tuned on target scans",
    "d": "fine-tuned on adapted + target scans",
}
MARKER = ".bench_adapt"


@dataclass(frozen=True)
class Plan:
    """How much of everything: sequences x scans of each set, and training steps."""

    source_sequences: int
    source_scans: int
    source_heldout_scans: int
    target_sequences: int
    target_scans: int
    test_sequences: int
    test_scans: int
    source_steps: int
    finetune_steps: int


DEFAULT = Plan(8, 6, 6, 2, 4, 3, 6, 1200, 300)
QUICK = Plan(2, 2, 2, 1, 2, 1, 2, 12, 6)


class Bench:
    """One run: its folders, its clock and the `rangeret` subprocesses it logs."""

    def __init__(self, out: Path) -> None:
        self.out = out
        self.work = out / "work"
        self.logs = self.work / "logs"
        self.start = time.perf_counter()
        self.times: dict[str, float] = {}

    def log(self, message: str) -> None:
        """Print a progress line with the time elapsed since the start."""
        print(f"[{time.perf_counter() - self.start:7.1f} s] {message}", flush=True)

    def rangeret(self, name: str, command: str, *args: str | Path) -> str:
        """Run `rangeret COMMAND -q ARGS` in a child process, its output logged to logs/NAME.log;
        returns its stdout and exits with the log's tail when it fails."""
        self.log(f"{name}: rangeret {command}")
        argv = [sys.executable, "-m", "rangeret.cli", command, "-q", *map(str, args)]
        started = time.perf_counter()
        child = subprocess.run(argv, cwd=REPO, capture_output=True, text=True, check=False)
        self.times[name] = time.perf_counter() - started
        log = self.logs / f"{name}.log"
        log.write_text(f"$ {' '.join(argv)}\n{child.stdout}\n{child.stderr}")
        if child.returncode:
            sys.exit(f"{name} failed ({log}):\n{(child.stdout + child.stderr)[-3000:]}")
        return child.stdout


def prepare(out: Path) -> Bench:
    """A fresh work folder under OUT (a previous run's is replaced; any other folder is refused)."""
    work = out / "work"
    if work.exists():
        if not (work / MARKER).exists():
            sys.exit(f"{work} exists and is not this benchmark's: choose another --out")
        shutil.rmtree(work)
    (work / "logs").mkdir(parents=True)
    (work / MARKER).write_text("")
    return Bench(out)


def write_target_profile(path: Path, names: dict[str, list[str]]) -> None:
    """The target sensor's profile: SemanticKITTI's labels, layout and normalisation with the
    target's beams, image and mounting; `names` gives its splits."""
    from rangeret.dataset.profiles import DatasetProfile, load_profile

    data = load_profile(SOURCE_PROFILE).to_dict()
    data.pop("benchmark", None)
    data["name"] = "sim-32beam"
    data["description"] = "A simulated 32-beam sensor, +10 to -30 degrees, 1.9 m high."
    data["sensor"].update(TARGET)
    data["splits"] = names
    path.write_text(DatasetProfile.from_dict(data, str(path)).to_yaml())


def write_identity_map(path: Path) -> None:
    """The label map `network raw id: data raw id` that keeps every SemanticKITTI class's id."""
    from rangeret.dataset.profiles import load_profile

    ids = load_profile(SOURCE_PROFILE).labels.class_raw_ids
    path.write_text("".join(f"{i}: {i}\n" for i in ids))


def sequences(first: int, count: int, scans: int) -> list[str]:
    """`rangeret simulate --sequences` items: `count` sequences from number `first`."""
    return [f"{first + i:02d}:{scans}" for i in range(count)]


def names(items: list[str]) -> list[str]:
    """The sequence names of `sequences()` items."""
    return [item.split(":")[0] for item in items]


def link_tree(root: Path, links: dict[str, Path]) -> None:
    """A SemanticKITTI-layout tree whose sequence folders link to other trees' sequences."""
    (root / "sequences").mkdir(parents=True)
    for name, target in links.items():
        (root / "sequences" / name).symlink_to(target.resolve(), target_is_directory=True)


def report(path: Path) -> dict:
    """The mIoU, the mIoU over the classes present in the ground truth and the main classes' IoU
    of an evaluation report, in %."""
    data = json.loads(path.read_text())
    gt = [sum(column) for column in zip(*data["confusion"], strict=True)]
    scored = [n for n, name in enumerate(data["class_names"]) if name in data["iou"]]
    present = [data["iou"][data["class_names"][n]] for n in scored if gt[n] > 0]
    return {
        "miou": 100 * data["miou"],
        "miou_present": 100 * sum(present) / len(present),
        "classes_present": len(present),
        "iou": {c: 100 * data["iou"][c] for c in MAIN_CLASSES},
        "points": data["num_points"],
        "scans": data["num_scans"],
    }


def chance_miou(path: Path) -> float:
    """The expected mIoU (%) of labels drawn uniformly at random, from a report's ground truth."""
    data = json.loads(path.read_text())
    gt = [sum(column) for column in zip(*data["confusion"], strict=True)]
    scored = [n for n, name in enumerate(data["class_names"]) if name in data["iou"]]
    total, k = sum(gt[n] for n in scored), len(scored)
    shares = [gt[n] / total for n in scored]
    return 100 * sum(p / (1 + p * (k - 1)) for p in shares) / k


def by_beams(
    profile_path: Path, data: Path, pred: Path, test: list[str], measured: set[int]
) -> dict:
    """Accuracy and mIoU over the classes present (%) of the target's test points, apart for the
    rows (beams) whose band the source measured and for the others."""
    import numpy as np

    from rangeret.dataset.layout import labels_dir, prediction_path, velodyne_dir
    from rangeret.dataset.profiles import load_profile
    from rangeret.dataset.projection import project_with
    from rangeret.evaluation.metrics import confusion_counts
    from rangeret.io.scans import read_labels, read_scan

    profile = load_profile(profile_path)
    labels, n = profile.labels, profile.num_classes
    counts = {"measured": np.zeros((n, n), np.int64), "unmeasured": np.zeros((n, n), np.int64)}
    for sequence in test:
        for scan in sorted(velodyne_dir(data, sequence, layout=profile.layout).glob("*.bin")):
            rows = project_with(read_scan(scan, record=profile.points), profile.projection).proj_y
            gt = labels.to_class(
                read_labels(
                    labels_dir(data, sequence, layout=profile.layout) / f"{scan.stem}.label"
                )
            )
            guess = labels.to_class(read_labels(prediction_path(pred, sequence, scan.stem)))
            inside = np.isin(rows, sorted(measured))
            for key, chosen in (("measured", inside), ("unmeasured", ~inside)):
                counts[key] += confusion_counts(guess[chosen], gt[chosen], n)
    scored = [c for c in range(n) if not labels.ignored[c]]
    result = {}
    for key, conf in counts.items():
        columns = conf[:, scored]
        tp, gt_n = columns[scored, range(len(scored))], columns.sum(axis=0)
        union = gt_n + columns[scored].sum(axis=1) - tp
        present = gt_n > 0
        result[key] = {
            "points": int(gt_n.sum()),
            "accuracy": float(100 * tp.sum() / max(gt_n.sum(), 1)),
            "miou_present": float(100 * (tp[present] / union[present]).mean())
            if present.any()
            else 0.0,
        }
    return result


def bar_chart(results: dict[str, dict], path: Path) -> None:
    """Grouped bars of the mIoU and the main classes' IoU of each variant."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = ["mIoU", *MAIN_CLASSES]
    width = 0.8 / len(results)
    fig, ax = plt.subplots(figsize=(10, 5))
    for i, (key, r) in enumerate(results.items()):
        values = [r["miou"], *(r["iou"][c] for c in MAIN_CLASSES)]
        xs = [g + (i - (len(results) - 1) / 2) * width for g in range(len(groups))]
        ax.bar(xs, values, width, label=f"{key}. {VARIANTS[key]}")
    ax.set_xticks(range(len(groups)), groups)
    ax.set_ylabel("IoU on the target's held-out scans (%)")
    ax.set_ylim(0, 100)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=2)
    ax.set_title("Adapting a 64-beam model to a 32-beam sensor (simulated scenes)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo (else the platform's)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def run(bench: Bench, plan: Plan) -> dict:
    """Every step of the benchmark; returns the figures and settings as plain data."""
    work = bench.work
    source, target, adapted, mixed = (work / n for n in ("source", "target", "adapted", "mixed"))
    profile, label_map = work / "sim-32beam.yaml", work / "identity.yaml"
    source_train = sequences(0, plan.source_sequences, plan.source_scans)
    source_heldout = sequences(90, 1, plan.source_heldout_scans)
    target_train = sequences(30, plan.target_sequences, plan.target_scans)
    target_test = sequences(20, plan.test_sequences, plan.test_scans)
    write_target_profile(
        profile, {"train": names(target_train), "valid": names(target_test), "test": []}
    )
    write_identity_map(label_map)
    offset = ("0", "0", f"{TARGET['mount_height'] - SOURCE_MOUNT:.2f}")

    bench.rangeret(
        "simulate-source",
        "simulate",
        "--out", source, "--profile", SOURCE_PROFILE, "--azimuth-steps", 2 * SOURCE_SIZE[1],
        "--seed", 1, "--sequences", *source_train, *source_heldout,
    )  # fmt: skip
    bench.rangeret(
        "simulate-target",
        "simulate",
        "--out", target, "--profile", profile, "--azimuth-steps", TARGET["width"], "--seed", 2,
        "--sequences", *target_train, *target_test,
    )  # fmt: skip

    model, overrides = NETWORK
    every_run = ("--val-sequences", "--loader-workers", 0, "--device", "cpu", "--seed", 0)
    bench.rangeret(
        "train-source",
        "train",
        "--dataset", source, "--profile", SOURCE_PROFILE, "--out", work / "run-source",
        "--height", SOURCE_SIZE[0], "--width", SOURCE_SIZE[1], "--model", model,
        *(a for o in overrides for a in ("--override", o)),
        "--train-sequences", *names(source_train), "--epochs", 100000,
        "--max-steps", plan.source_steps, *every_run,
    )  # fmt: skip
    checkpoints = {"a": work / "run-source" / "last.pt"}

    bench.rangeret(
        "predict-source-heldout",
        "predict",
        "--checkpoint", checkpoints["a"], "--dataset", source,
        "--sequences", *names(source_heldout), "--out", work / "pred-source-heldout",
    )  # fmt: skip
    source_report = work / "source-heldout.json"
    bench.rangeret(
        "evaluate-source-heldout",
        "evaluate",
        "--profile", SOURCE_PROFILE, "--dataset", source,
        "--predictions", work / "pred-source-heldout",
        "--sequences", *names(source_heldout), "--json", source_report,
    )  # fmt: skip

    bench.rangeret(
        "adapt",
        "adapt",
        "--dataset", source, "--profile", SOURCE_PROFILE, "--to-profile", profile,
        "--out", adapted, "--sequences", *names(source_train), "--sensor-offset", *offset,
    )  # fmt: skip
    adapted_scans = plan.source_sequences * plan.source_scans
    repeats = max(1, round(adapted_scans / (plan.target_sequences * plan.target_scans)))
    links = {n: adapted / "sequences" / n for n in names(source_train)}
    target_names = names(target_train)
    for k in range(repeats * len(target_names)):
        links[f"{50 + k:02d}"] = target / "sequences" / target_names[k % len(target_names)]
    link_tree(mixed, links)

    adapt_record = json.loads((adapted / "adapt.json").read_text())
    unmeasured = set(adapt_record["unmeasured_beams"])
    measured = set(range(TARGET["height"])) - unmeasured
    finetunes = {
        "b": (adapted, names(source_train)),
        "c": (target, target_names),
        "d": (mixed, list(links)),
    }
    low, peak = FINETUNE_LR
    for key, (root, train) in finetunes.items():
        bench.rangeret(
            f"finetune-{key}",
            "train",
            "--dataset", root, "--profile", profile, "--out", work / f"run-{key}",
            "--init-from", checkpoints["a"], "--train-sequences", *train,
            "--epochs", 100000, "--max-steps", plan.finetune_steps,
            "--lr", low, "--max-lr", peak, *every_run,
        )  # fmt: skip
        checkpoints[key] = work / f"run-{key}" / "last.pt"

    results, reports = {}, []
    for key, checkpoint in checkpoints.items():
        other = ("--label-map", label_map) if key == "a" else ()
        bench.rangeret(
            f"predict-{key}",
            "predict",
            "--checkpoint", checkpoint, "--profile", profile, *other, "--dataset", target,
            "--sequences", *names(target_test), "--out", work / f"pred-{key}",
        )  # fmt: skip
        reports.append(work / f"target-{key}.json")
        bench.rangeret(
            f"evaluate-{key}",
            "evaluate",
            "--profile", profile, "--dataset", target, "--predictions", work / f"pred-{key}",
            "--sequences", *names(target_test), "--json", reports[-1],
        )  # fmt: skip
        results[key] = report(reports[-1]) | {"variant": VARIANTS[key]}
        results[key]["by_beams"] = by_beams(
            profile, target, work / f"pred-{key}", names(target_test), measured
        )
    comparison = bench.rangeret("compare", "compare", *reports, "--out", bench.out / "compare.png")

    train_times = {k: v for k, v in bench.times.items() if k.startswith(("train", "finetune"))}
    return {
        "plan": asdict(plan),
        "source": {
            "profile": SOURCE_PROFILE,
            "size": list(SOURCE_SIZE),
            "mount_height": SOURCE_MOUNT,
            "train_sequences": source_train,
            "heldout_sequences": source_heldout,
            "heldout": report(source_report),
            "heldout_chance_miou": chance_miou(source_report),
        },
        "target": {
            **TARGET,
            "train_sequences": target_train,
            "test_sequences": target_test,
            "test_chance_miou": chance_miou(reports[0]),
        },
        "adapt": {
            "sensor_offset": [float(v) for v in offset],
            "counts": adapt_record.get("counts"),
            "unmeasured_beams": sorted(unmeasured),
        },
        "mixed_tree": {"target_repeats": repeats, "sequences": len(links)},
        "network": {"model": model, "overrides": list(overrides)},
        "finetune": {"steps": plan.finetune_steps, "lr": low, "max_lr": peak},
        "results": results,
        "comparison": comparison,
        "step_seconds": bench.times,
        "train_seconds": train_times,
        "cpu": cpu_model(),
        "cpu_cores": os.cpu_count(),
    }


def print_table(figures: dict) -> None:
    """The table of a-d, with the source network's own held-out score for reference."""
    held = figures["source"]["heldout"]
    print(
        f"\nsource network on held-out source scans: mIoU {held['miou']:.1f} % "
        f"({held['miou_present']:.1f} % over the {held['classes_present']} classes present; "
        f"uniform random labels: {figures['source']['heldout_chance_miou']:.1f} %)"
    )
    if held["miou"] < 5 * figures["source"]["heldout_chance_miou"]:
        print(
            "warning: the source network is barely above chance, so a-d say little about adapting"
        )
    print(
        f"target held-out scans, uniform random labels: {figures['target']['test_chance_miou']:.1f} %\n"
    )
    header = f"{'':40} {'mIoU':>6} {'present':>8}" + "".join(f" {c:>10}" for c in MAIN_CLASSES)
    print(header)
    for key, r in figures["results"].items():
        row = f"{key}. {r['variant']:37} {r['miou']:6.1f} {r['miou_present']:8.1f}"
        print(row + "".join(f" {r['iou'][c]:10.1f}" for c in MAIN_CLASSES))
    print("\n(IoU %; 'present': mIoU over the classes present in the target's test scans)\n")
    beams = figures["adapt"]["unmeasured_beams"]
    first = next(iter(figures["results"].values()))["by_beams"]
    print(
        f"by beam: the {TARGET['height'] - len(beams)} beams inside the source's field of view "
        f"({first['measured']['points']:,} test points) and the {len(beams)} outside it "
        f"({first['unmeasured']['points']:,}: rows {', '.join(map(str, beams))})"
    )
    print(f"{'':40} {'inside: acc':>11} {'mIoU':>6} {'outside: acc':>12} {'mIoU':>6}")
    for key, r in figures["results"].items():
        inside, outside = r["by_beams"]["measured"], r["by_beams"]["unmeasured"]
        print(
            f"{key}. {r['variant']:37} {inside['accuracy']:11.1f} {inside['miou_present']:6.1f} "
            f"{outside['accuracy']:12.1f} {outside['miou_present']:6.1f}"
        )
    print("\n(accuracy and mIoU over the classes present, %)\n")
    print(figures["comparison"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--out",
        type=Path,
        default=REPO / "runs" / "bench-adapt",
        help="where the figures go (OUT/adapt.json, OUT/adapt.png, OUT/compare.png) and the "
        "run's data and checkpoints (OUT/work, replaced on each run; default: runs/bench-adapt)",
    )
    parser.add_argument(
        "--quick", action="store_true", help="a tiny run (a few scans and steps) for smoke checks"
    )
    args = parser.parse_args()
    plan = QUICK if args.quick else DEFAULT
    out = args.out.resolve()
    bench = prepare(out)
    bench.log(f"{'quick' if args.quick else 'default'} run into {out}: {plan}")
    figures = run(bench, plan)
    figures["quick"] = args.quick
    figures["wall_seconds"] = time.perf_counter() - bench.start
    (out / "adapt.json").write_text(json.dumps(figures, indent=2) + "\n")
    bar_chart(figures["results"], out / "adapt.png")
    print_table(figures)
    bench.log(f"done: {out / 'adapt.json'}, {out / 'adapt.png'}, {out / 'compare.png'}")


if __name__ == "__main__":
    main()
