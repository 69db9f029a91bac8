"""A toy benchmark from outside the library, registered the documented way (an entry point of the
group `rangeret.benchmarks`; `register` writes the distribution's metadata into a folder that
goes on the path).

Its archive holds `toy/<sequence>/<scan>.label` for every scan of the profile's `test` split and
`toy.json` (the scan count and the `--toy-note` option); its validator checks both against the
dataset. A gateway job's zip is `toy/...` too, with `toy.json` naming the checkpoint.
"""

from __future__ import annotations

import argparse
import json
import zipfile
from pathlib import Path

from rangeret.dataset.layout import ScanEntry
from rangeret.dataset.profiles import DatasetProfile
from rangeret.dataset.selection import select_dataset
from rangeret.io.scans import scan_num_points
from rangeret.submission.archives import SubmissionCheck, SubmissionError
from rangeret.submission.benchmark import ArchiveRequest, Benchmark, JobPredictions

ENTRY_POINTS = "[rangeret.benchmarks]\ntoy = tests.support.toy_benchmark:TOY\n"


def register(folder: Path) -> Path:
    """A distribution's metadata declaring the toy entry point, in `folder`; put `folder` on the
    path (sys.path, PYTHONPATH) to register it."""
    dist = folder / "rangeret_toy_benchmark-0.1.dist-info"
    dist.mkdir(parents=True, exist_ok=True)
    (dist / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: rangeret-toy-benchmark\nVersion: 0.1\n"
    )
    (dist / "entry_points.txt").write_text(ENTRY_POINTS)
    return folder


def _member(entry: ScanEntry) -> str:
    return f"toy/{entry.sequence}/{entry.name}.label"


class ToyBenchmark(Benchmark):
    """Every test scan's prediction under `toy/`, counted in `toy.json`."""

    name = "toy"
    title = "Toy"
    writes_archives = True

    def add_arguments(self, parser: argparse.ArgumentParser, *, writing: bool) -> None:
        if writing:
            parser.add_argument_group("Toy").add_argument("--toy-note", metavar="TEXT")

    def option_dests(self, *, writing: bool) -> tuple[str, ...]:
        return ("toy_note",) if writing else ()

    def _test_scans(self, dataset: Path, profile: DatasetProfile) -> list[ScanEntry]:
        selection = select_dataset(
            dataset, layout=profile.layout, labels=profile.labels, split="test"
        )
        return selection.scans()

    def write_archive(self, request: ArchiveRequest) -> SubmissionCheck:
        predictions = request.predictions_tree()
        scans = self._test_scans(request.dataset, request.profile)
        missing = [e.key for e in scans if not e.prediction_in(predictions).is_file()]
        if missing:
            raise SubmissionError([f"no prediction for {key}" for key in missing])
        with zipfile.ZipFile(request.archive, "w") as zf:
            for entry in scans:
                zf.write(entry.prediction_in(predictions), _member(entry))
            note = request.options.get("toy_note")
            zf.writestr("toy.json", json.dumps({"scans": len(scans), "note": note}))
            zf.writestr("description.txt", request.description)
        check = self.validate_archive(request)
        check.raise_for_problems()
        return check

    def validate_archive(self, request: ArchiveRequest) -> SubmissionCheck:
        scans = self._test_scans(request.dataset, request.profile)
        check = SubmissionCheck(path=Path(request.archive), partial=request.allow_partial)
        check.sequences = sorted({e.sequence for e in scans})
        with zipfile.ZipFile(request.archive) as zf:
            names = set(zf.namelist())
            manifest = json.loads(zf.read("toy.json")) if "toy.json" in names else {}
            if manifest.get("scans") != len(scans):
                check.problems.append(f"toy.json counts {manifest.get('scans')} of {len(scans)}")
            for entry in scans:
                member = _member(entry)
                points = scan_num_points(entry.scan_path, record=request.profile.points)
                if member not in names:
                    check.problems.append(f"{member} is missing")
                elif zf.getinfo(member).file_size != 4 * points:
                    check.problems.append(f"{member} does not hold {points} labels")
                else:
                    check.scans += 1
        return check

    def write_job_zip(self, job: JobPredictions) -> None:
        with zipfile.ZipFile(job.path, "w") as zf:
            for entry in job.entries:
                zf.write(entry.prediction_in(job.pred_root), _member(entry))
            zf.writestr("toy.json", json.dumps({"scans": len(job.entries), "sha256": job.sha256}))
            zf.writestr("description.txt", job.description)


TOY = ToyBenchmark()
