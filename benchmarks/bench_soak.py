"""Soak run of the HTTP gateway: steady single-scan load for a bounded time, and the server's memory.

Starts a gateway of its own (`python -m service` on a free loopback port, its state in a temporary
folder; by default the small published-layout weights of the test vectors at 32 x 256), or attaches
to a running one with `--url`. After a warm-up, `--clients` clients (one thread and one httpx
client each) loop POST /v1/scans with the real SemanticKITTI scan of tests/data (or a random scan
of `--points` points; every `--json-every`-th request asks for JSON) for `--seconds` seconds, all
on loopback. Reported: requests, scans/s, p50 / p95 / p99 / max latency of the 200 answers, the
answers by status (200, 503 from a full queue or a failed batch, other 4xx, other 5xx, transport
errors), the gateway process's resident memory (VmRSS; Ray actors are other processes) after the
warm-up, after the run and sampled every second in between, the mean network batch of the run
from /metrics, and a verdict on whether the memory grew by more than `--rss-growth-mib` after the
warm-up. With `--hostile-every N`, once the warm-up of good requests is over, every N-th request
of each client sends one of the tests' hostile point-cloud bodies in turn (decoded-size bombs,
colliding columns, corrupt LZF, non-finite values...), whose answers must all be 400 or 413.
A printed verdict, not an assertion; run by hand (`--help` for every option), e.g.

    python benchmarks/bench_soak.py --clients 8 --seconds 600 --warmup-s 10 --out soak.json
    python benchmarks/bench_soak.py --clients 32 --seconds 60 --warmup-s 10 --hostile-every 4 \
        --rss-growth-mib 100
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import numpy as np
from _common import REAL_SCAN, REPO, require_real_scan
from _gateway import StartedGateway, rss_mib, start_gateway

OCTET = "application/octet-stream"
RECORD_FIELDS = 4  # float32 x, y, z, remission: the SemanticKITTI point record this run sends
MAX_BACKOFF_S = 1.0  # longest a client honours a 503's Retry-After before trying again
KINDS = ("200", "503", "4xx", "5xx other", "transport")


# The gateway -------------------------------------------------------------------------------------


def launch(args: argparse.Namespace, tmp: Path) -> StartedGateway:
    """A gateway process with the run's network options, once it answers /healthz with 200."""
    net: list[str] = []
    height, width = args.height, args.width
    if args.checkpoint == "small":
        import torch
        from _common import small_state_dict

        weights = tmp / "cir-small.pt"
        torch.save(small_state_dict(), weights)
        net += ["--checkpoint", str(weights)]
        height, width = height or 32, width or 256  # the resolution of the test vectors
        weights_name = "small rangeret-cir test weights"
    elif args.checkpoint == "demo":
        weights_name = "bundled demo weights"  # no --checkpoint: the gateway's default
    else:
        net += ["--checkpoint", str(Path(args.checkpoint).resolve())]
        weights_name = Path(args.checkpoint).name
    for option, value in (
        ("--height", height),
        ("--width", width),
        ("--device", args.device),
        ("--precision", args.precision),
        ("--batch-size", args.batch_size),
        ("--batch-wait-ms", args.batch_wait_ms),
    ):
        if value is not None:
            net += [option, str(value)]
    settings = {"RANGERET_STATE_DIR": str(tmp / "state")}
    for item in args.env:
        key, sep, value = item.partition("=")
        if not sep or not key.startswith("RANGERET_"):
            sys.exit(f"--env takes RANGERET_NAME=VALUE, got {item!r}")
        settings[key] = value
    shape = f"{height}x{width}" if height and width else "the profile's resolution"
    return start_gateway(net, settings, tmp / "gateway.log", f"{weights_name}, {shape}")


def batch_histogram(url: str, headers: dict[str, str]) -> tuple[float, float] | None:
    """(sum, count) of the rangeret_batch_scans histogram from /metrics, or None if absent."""
    try:
        text = httpx.get(url + "/metrics", headers=headers, timeout=10).text
    except httpx.HTTPError:
        return None
    found: dict[str, float] = {}
    for line in text.splitlines():
        name, _, value = line.partition(" ")
        if name in ("rangeret_batch_scans_sum", "rangeret_batch_scans_count"):
            found[name] = float(value.split()[0])
    if len(found) < 2:
        return None
    return found["rangeret_batch_scans_sum"], found["rangeret_batch_scans_count"]


# The load ----------------------------------------------------------------------------------------


@dataclass
class Answer:
    """One request: when it ended (perf_counter), what came back, how long it took."""

    end: float
    kind: str
    status: int | None
    latency: float
    good: bool = True  # a 200 whose body has the expected size or shape
    hostile: bool = False  # a hostile body, whose right answer is a 400 or 413


@dataclass
class Load:
    """Everything the client threads share: what to send, where, and when to stop; with
    `hostile_every`, once `hostile_on` is set, every so many requests send a hostile body."""

    url: str
    body: bytes
    points: int
    headers: dict[str, str]
    json_every: int
    timeout: float
    hostile: list[tuple[str, bytes, str]] = field(default_factory=list)
    hostile_every: int = 0
    hostile_on: threading.Event = field(default_factory=threading.Event)
    stop: threading.Event = field(default_factory=threading.Event)
    answers: list[list[Answer]] = field(default_factory=list)
    examples: dict[str, str] = field(default_factory=dict)  # the first answer of each failure

    def note(self, key: str, text: str) -> None:
        self.examples.setdefault(key, " ".join(text.split())[:300])


def kind_of(status: int) -> str:
    if status == 200:
        return "200"
    if status == 503:
        return "503"
    if 400 <= status < 500:
        return "4xx"
    return "5xx other"


def client_loop(load: Load, answers: list[Answer]) -> None:
    """Send the scan again and again until told to stop; a 503 waits for its Retry-After."""
    octet = {**load.headers, "Content-Type": OCTET}
    as_json = {**octet, "Accept": "application/json"}
    n = 0
    with httpx.Client(base_url=load.url, timeout=load.timeout) as client:
        while not load.stop.is_set():
            n += 1
            if load.hostile_on.is_set() and load.hostile_every and n % load.hostile_every == 0:
                send_hostile(client, load, answers, n // load.hostile_every)
                continue
            want_json = load.json_every > 0 and n % load.json_every == 0
            start = time.perf_counter()
            try:
                r = client.post(
                    "/v1/scans", content=load.body, headers=as_json if want_json else octet
                )
            except httpx.HTTPError as exc:
                end = time.perf_counter()
                answers.append(Answer(end, "transport", None, end - start))
                load.note("transport", f"{type(exc).__name__}: {exc}")
                load.stop.wait(0.2)
                continue
            end = time.perf_counter()
            kind = kind_of(r.status_code)
            good = True
            if kind == "200":
                if want_json:
                    try:
                        good = r.json().get("num_points") == load.points
                    except ValueError:
                        good = False
                else:
                    good = len(r.content) == 4 * load.points
            answers.append(Answer(end, kind, r.status_code, end - start, good))
            if kind != "200":
                load.note(str(r.status_code), r.text)
            elif not good:
                load.note("bad 200", f"{len(r.content)} bytes for {load.points} points")
            if kind == "503":
                try:
                    wait = float(r.headers.get("Retry-After", "0.1"))
                except ValueError:
                    wait = 0.1
                load.stop.wait(min(max(wait, 0.0), MAX_BACKOFF_S))
            elif kind != "200":
                load.stop.wait(0.1)


def send_hostile(client: httpx.Client, load: Load, answers: list[Answer], i: int) -> None:
    """Send the `i`-th hostile body (in turn); a 400 or 413 is its right answer."""
    name, body, media = load.hostile[i % len(load.hostile)]
    start = time.perf_counter()
    try:
        r = client.post("/v1/scans", content=body, headers={**load.headers, "Content-Type": media})
    except httpx.HTTPError as exc:
        end = time.perf_counter()
        answers.append(Answer(end, "transport", None, end - start, hostile=True))
        load.note("transport", f"{name}: {type(exc).__name__}: {exc}")
        return
    end = time.perf_counter()
    right = r.status_code in (400, 413)
    answers.append(Answer(end, kind_of(r.status_code), r.status_code, end - start, right, True))
    if not right:
        load.note(f"hostile {name} {r.status_code}", r.text)


def hostile_bodies() -> list[tuple[str, bytes, str]]:
    """The hostile point-cloud bodies of the project's tests (name, body, Content-Type): headers
    that ask for far more than the limits, columns that collide, short or corrupt data."""
    sys.path.insert(0, str(REPO))
    from tests.support import hostile_files as h

    pcd, las = "application/x-pcd", "application/vnd.las"
    nan = np.full((1000, RECORD_FIELDS), np.nan, np.float32).tobytes()
    return [
        ("wide compressed PCD", h.wide_compressed_pcd(20_000), pcd),
        ("COUNT 20,000,000 PCD", h.count_bomb_pcd(), pcd),
        ("colliding PCD columns", h.colliding_pcd(), pcd),
        ("short ASCII PCD", h.short_ascii_pcd(), pcd),
        ("corrupt LZF PCD", h.bad_lzf_pcd(overflowing=False), pcd),
        ("overflowing LZF PCD", h.bad_lzf_pcd(overflowing=True), pcd),
        ("a million VLRs LAS", h.vlr_bomb_las(), las),
        ("2^40 points LAZ", h.huge_laz(), "application/vnd.laszip"),
        ("wide PLY header", h.wide_ply_header(2_000_000), "application/x-ply"),
        ("non-finite .bin", nan, OCTET),
    ]


def sample_rss(pid: int | None, t0: float, stop: threading.Event, out: list[list[float]]) -> None:
    """Every second until `stop`: [seconds since t0, VmRSS MiB]."""
    while not stop.wait(1.0):
        mib = rss_mib(pid)
        if mib is not None:
            out.append([round(time.perf_counter() - t0, 2), round(mib, 1)])


def make_body(points: int | None, seed: int) -> tuple[bytes, int, str]:
    """The request body, its number of points, and a description."""
    if points is None:
        require_real_scan()
        body = REAL_SCAN.read_bytes()
        n = len(body) // (4 * RECORD_FIELDS)
        return body, n, f"the real scan of tests/data ({n:,} points)"
    rng = np.random.default_rng(seed)
    azimuth = rng.uniform(-np.pi, np.pi, points)
    distance = rng.uniform(2.0, 60.0, points)
    scan = np.stack(
        [
            distance * np.cos(azimuth),
            distance * np.sin(azimuth),
            rng.uniform(-2.5, 2.0, points),
            rng.uniform(0.0, 1.0, points),
        ],
        axis=1,
    ).astype("<f4")
    return scan.tobytes(), points, f"a random scan of {points:,} points"


# The report --------------------------------------------------------------------------------------


def ms(values: np.ndarray, q: float) -> float | None:
    return round(float(np.percentile(values, q)) * 1e3, 1) if len(values) else None


def summarise(
    args: argparse.Namespace,
    answers: list[Answer],
    window: float,
    rss_before: float | None,
    rss_after: float | None,
    samples: list[list[float]],
    batch_delta: tuple[float, float] | None,
) -> dict:
    """The run's figures as a JSON-ready dict."""
    counts = Counter(a.kind for a in answers)
    ok = np.array([a.latency for a in answers if a.kind == "200"])
    rss_values = [mib for _, mib in samples]
    growth = None if rss_before is None or rss_after is None else round(rss_after - rss_before, 1)
    mean_batch = batches = None
    if batch_delta:
        batches = int(batch_delta[1])
        mean_batch = round(batch_delta[0] / batch_delta[1], 2) if batch_delta[1] > 0 else None
    return {
        "clients": args.clients,
        "seconds": round(window, 1),
        "warmup_s": args.warmup_s,
        "requests": len(answers),
        "scans_per_s": round(counts["200"] / window, 2) if window > 0 else None,
        "latency_ms": {
            "p50": ms(ok, 50),
            "p95": ms(ok, 95),
            "p99": ms(ok, 99),
            "max": round(float(ok.max()) * 1e3, 1) if len(ok) else None,
        },
        "status": {kind: counts[kind] for kind in KINDS},
        "status_codes": dict(
            sorted(Counter(str(a.status) for a in answers if a.status is not None).items())
        ),
        "bad_200": sum(1 for a in answers if a.kind == "200" and not a.good),
        "rss_mib": {
            "before": None if rss_before is None else round(rss_before, 1),
            "after": None if rss_after is None else round(rss_after, 1),
            "growth": growth,
            "min": min(rss_values) if rss_values else None,
            "median": round(statistics.median(rss_values), 1) if rss_values else None,
            "max": max(rss_values) if rss_values else None,
            "samples": samples,
        },
        "mean_batch": mean_batch,
        "batches": batches,
        "rss_growth_threshold_mib": args.rss_growth_mib,
        "rss_grew": None if growth is None else growth > args.rss_growth_mib,
    }


def fmt(value: float | int | None, spec: str = "") -> str:
    return "unknown" if value is None else format(value, spec)


def print_report(r: dict) -> None:
    lat, rss, st = r["latency_ms"], r["rss_mib"], r["status"]
    rows = [
        ("clients", fmt(r["clients"])),
        ("seconds", fmt(r["seconds"], ".1f")),
        ("requests", fmt(r["requests"], ",")),
        ("scans/s", fmt(r["scans_per_s"], ".2f")),
        (
            "latency of 200s, ms",
            f"p50 {fmt(lat['p50'])}   p95 {fmt(lat['p95'])}   p99 {fmt(lat['p99'])}   "
            f"max {fmt(lat['max'])}",
        ),
        ("status 200", fmt(st["200"], ",")),
        ("status 503", fmt(st["503"], ",")),
        ("status 4xx", fmt(st["4xx"], ",")),
        ("status 5xx other", fmt(st["5xx other"], ",")),
        ("transport errors", fmt(st["transport"], ",")),
        ("200s with a wrong body", fmt(r["bad_200"], ",")),
        ("RSS before, MiB", fmt(rss["before"], ".1f")),
        ("RSS after, MiB", fmt(rss["after"], ".1f")),
        ("RSS growth, MiB", fmt(rss["growth"], "+.1f")),
        (
            "RSS over the run, MiB",
            f"min {fmt(rss['min'], '.1f')}   median {fmt(rss['median'], '.1f')}   "
            f"max {fmt(rss['max'], '.1f')}   ({len(rss['samples'])} samples)",
        ),
        (
            "mean batch (/metrics)",
            "not in /metrics"
            if r["batches"] is None
            else f"{r['mean_batch']:.2f} ({r['batches']:,} batches)"
            if r["batches"]
            else "no batch in the run",
        ),
    ]
    width = max(len(name) for name, _ in rows)
    for name, value in rows:
        print(f"  {name:<{width}}  {value}")
    for key, text in sorted(r["examples"].items()):
        print(f"  first {key} answer: {text}")
    threshold = r["rss_growth_threshold_mib"]
    if r["rss_grew"] is None:
        print("verdict: RSS unknown (give --pid with --url), no verdict on memory growth")
    elif r["rss_grew"]:
        print(
            f"verdict: RSS GREW by {rss['growth']:.1f} MiB after warm-up, "
            f"more than the {threshold:g} MiB threshold"
        )
    else:
        print(
            f"verdict: RSS grew by {rss['growth']:+.1f} MiB after warm-up, "
            f"within the {threshold:g} MiB threshold"
        )


# The run -----------------------------------------------------------------------------------------


def wait_until(end: float, gw: StartedGateway | None) -> int | None:
    """Sleep until `end` (perf_counter); the gateway's exit code if it exits before, else None."""
    while (now := time.perf_counter()) < end:
        if gw and gw.proc.poll() is not None:
            return gw.proc.returncode
        time.sleep(min(0.5, end - now))
    return None


def soak(args: argparse.Namespace, url: str, pid: int | None, gw: StartedGateway | None) -> dict:
    """Warm up, load for `--seconds`, sample memory; the figures."""
    headers = {"Authorization": f"Bearer {args.token}"} if args.token else {}
    try:
        health = httpx.get(url + "/healthz", headers=headers, timeout=10).json()
    except (httpx.HTTPError, ValueError) as exc:
        sys.exit(f"{url}/healthz did not answer: {exc}")
    fields = health.get("point_fields") or []
    if fields and len(fields) != RECORD_FIELDS:
        sys.exit(
            f"the gateway serves {health.get('profile')} ({', '.join(fields)}); this benchmark "
            "sends SemanticKITTI records (x, y, z, remission)"
        )
    body, points, what = make_body(args.points, args.seed)
    load = Load(url, body, points, headers, args.json_every, args.timeout)
    if args.hostile_every:
        load.hostile, load.hostile_every = hostile_bodies(), args.hostile_every
    devices = ", ".join(sorted({str(w.get("device")) for w in health.get("workers") or []})) or "?"
    mix = f", 1 request in {args.json_every} asking for JSON" if args.json_every else ""
    if args.hostile_every:
        mix += (
            f", after the warm-up 1 request in {args.hostile_every} a hostile body "
            f"({len(load.hostile)} kinds in turn)"
        )
    print(
        f"soak: {args.clients} clients x {args.seconds:g} s after {args.warmup_s:g} s of warm-up, "
        f"{what}{mix}, {url}"
        + (f" ({gw.description})" if gw else "")
        + f", pid {fmt(pid)}, {health.get('backend', '?')} backend on {devices}, "
        f"{os.cpu_count()} CPUs"
    )
    threads = []
    for _ in range(args.clients):
        answers: list[Answer] = []
        load.answers.append(answers)
        threads.append(threading.Thread(target=client_loop, args=(load, answers), daemon=True))
    for t in threads:
        t.start()
    try:
        died = wait_until(time.perf_counter() + args.warmup_s, gw)
        t0 = time.perf_counter()
        rss_before = rss_mib(pid)
        load.hostile_on.set()
        batch_before = batch_histogram(url, headers)
        samples: list[list[float]] = [] if rss_before is None else [[0.0, round(rss_before, 1)]]
        sampling = threading.Event()
        sampler = threading.Thread(
            target=sample_rss, args=(pid, t0, sampling, samples), daemon=True
        )
        sampler.start()
        if died is None:
            died = wait_until(t0 + args.seconds, gw)
        t1 = time.perf_counter()
        rss_after = rss_mib(pid)
        sampling.set()
        sampler.join(5)
        if rss_after is not None:
            samples.append([round(t1 - t0, 2), round(rss_after, 1)])
    finally:
        load.stop.set()
    for t in threads:
        t.join(args.timeout + 5)
    batch_after = batch_histogram(url, headers)
    batch_delta = None
    if batch_after and batch_before:
        batch_delta = (batch_after[0] - batch_before[0], batch_after[1] - batch_before[1])
    elif batch_after:
        batch_delta = batch_after
    window = [a for per in load.answers for a in per if t0 <= a.end <= t1]
    hostile = [a for a in window if a.hostile]
    report = summarise(
        args,
        [a for a in window if not a.hostile],
        t1 - t0,
        rss_before,
        rss_after,
        samples,
        batch_delta,
    )
    if args.hostile_every:
        report["hostile"] = {
            "sent": len(hostile),
            "400 or 413": sum(a.good for a in hostile),
            "other": dict(Counter(str(a.status) for a in hostile if not a.good)),
        }
        print(
            f"hostile bodies: {len(hostile)} sent, {report['hostile']['400 or 413']} answered "
            f"400 or 413, others: {report['hostile']['other'] or 'none'}"
        )
    report.update(
        url=url, scan=what, points=points, json_every=args.json_every, examples=load.examples
    )
    if gw and (report["status"]["5xx other"] or died is not None):
        report["gateway_log_tail"] = gw.log_tail()
    if died is not None:
        report["gateway_exit_code"] = died
        print(f"the gateway exited with {died} during the run")
    return report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    load = parser.add_argument_group("load")
    load.add_argument("--clients", type=int, default=8, help="concurrent clients (default 8)")
    load.add_argument(
        "--seconds", type=float, default=60.0, help="measured time after warm-up (default 60)"
    )
    load.add_argument(
        "--warmup-s", type=float, default=10.0, help="load before measuring (default 10)"
    )
    load.add_argument(
        "--points", type=int, help="send a random scan of N points instead of the real scan"
    )
    load.add_argument(
        "--json-every",
        type=int,
        default=0,
        metavar="K",
        help="ask every K-th request of each client for JSON (default 0: never)",
    )
    load.add_argument("--seed", type=int, default=0, help="seed of the random scan")
    load.add_argument(
        "--hostile-every",
        type=int,
        default=0,
        metavar="N",
        help="after the warm-up, every N-th request of each client sends one of the tests' "
        "hostile point-cloud bodies, whose answer must be a 400 or 413 (default 0: none)",
    )
    load.add_argument(
        "--timeout", type=float, default=120.0, help="seconds one request may take (default 120)"
    )
    load.add_argument(
        "--rss-growth-mib",
        type=float,
        default=50.0,
        help="RSS growth after warm-up above which the verdict says it grew (default 50)",
    )
    load.add_argument("--out", type=Path, metavar="FILE.json", help="also write the figures here")
    attach = parser.add_argument_group("a running gateway")
    attach.add_argument("--url", help="load this gateway instead of starting one")
    attach.add_argument("--pid", type=int, help="its process id, to read its RSS")
    attach.add_argument(
        "--token",
        default=os.environ.get("RANGERET_API_TOKEN") or None,
        help="bearer token (default: RANGERET_API_TOKEN)",
    )
    own = parser.add_argument_group("a gateway started here")
    own.add_argument(
        "--checkpoint",
        default="small",
        help="weights: a file, 'demo' (the bundled demo weights) or 'small' (the 32 x 256 "
        "rangeret-cir test weights of tests/data; the default)",
    )
    own.add_argument("--height", type=int, help="range image rows (small weights: 32)")
    own.add_argument("--width", type=int, help="range image columns (small weights: 256)")
    own.add_argument("--device", choices=["auto", "cpu", "cuda"], help="default: auto")
    own.add_argument(
        "--precision",
        choices=["auto", "fp32", "fp16", "bf16"],
        help="the network's precision (default: auto)",
    )
    own.add_argument("--batch-size", type=int, help="RANGERET_BATCH_SIZE (default 1)")
    own.add_argument("--batch-wait-ms", type=float, help="RANGERET_BATCH_WAIT_MS (default 10)")
    own.add_argument(
        "--env",
        action="append",
        default=[],
        metavar="RANGERET_NAME=VALUE",
        help="a gateway setting, e.g. RANGERET_MAX_QUEUED_SCANS=4 (repeatable)",
    )
    args = parser.parse_args()
    if args.clients < 1 or args.seconds <= 0 or args.warmup_s < 0:
        parser.error("--clients must be at least 1, --seconds positive, --warmup-s not negative")
    if args.points is not None and args.points < 1:
        parser.error("--points must be at least 1")

    if args.url:
        report = soak(args, args.url.rstrip("/"), args.pid, None)
    else:
        with tempfile.TemporaryDirectory(prefix="bench-soak-") as tmp:
            gw = launch(args, Path(tmp))
            try:
                report = soak(args, gw.url, gw.proc.pid, gw)
            finally:
                report_stop = gw.stop()
            report["gateway_stop"] = report_stop
    print_report(report)
    if "gateway_log_tail" in report:
        print(f"the gateway's log ends with:\n{report['gateway_log_tail']}")
    if args.url is None:
        print(f"gateway {report['gateway_stop']}")
    if args.out:
        args.out.write_text(json.dumps(report, indent=2) + "\n")
        print(f"figures written to {args.out}")


if __name__ == "__main__":
    main()
