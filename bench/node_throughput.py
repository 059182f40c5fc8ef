"""Live node throughput: sustained input rate, loss, latency and CPU over real DDS.

For each configuration (input kind x executor x rate) it starts `touchdown_estimator`
in its own process, publishes a repeating drop cycle (20 ms levitated, 150 ms of
the model's own touchdown, back to levitation in 5 ms, 25 ms levitated: the EKF
runs on ~80 % of the samples) from a second process stamped with the wall clock,
and listens in this process to the estimates:

* loss: samples the node received and placed (its /diagnostics counts: received,
  gaps, missing samples) against the samples sent;
* latency from sample stamp to published estimate, p50 and p99 over the whole run
  (the node's own histogram, reported in /diagnostics), and from sample stamp to the
  estimate received by this process's subscriber (includes the DDS delivery);
* CPU of the node process (utime + stime over the run, % of one core).

Per-sample input is geometry_msgs/PointStamped on /amb/displacement with the
per-sample /touchdown/* outputs (this process subscribes to /touchdown/contact_force);
batched input is sensor_msgs/PointCloud2 (100 samples per message) with the batched
output (/touchdown/estimate_batch), sensor.sample_period set to the input rate. A case
may choose the output (`...:cycle:batch`: per-sample input, batched output, which this
process then subscribes to).

`--busy-loops N` runs N CPU-bound processes at normal priority beside every case (other
load on the machine, e.g. to see what real-time priority protects the node from);
`--stall S` stops the node process for S s halfway through each case (what a stall loses).

Run: .venv/bin/python bench/node_throughput.py [--duration 60] [--cases ...] [--busy-loops N] [--stall S]
Prints a markdown table (paste it into docs/node.md with the date).
"""
from __future__ import annotations

import argparse
import array
import json
import os
import signal
import struct
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

BATCH = 100  # samples per PointCloud2 in batched mode
LEVITATED_BEFORE_DROP = 0.02  # s of levitation at the start of each cycle
SINK_POLL = 0.0005  # s between two takes of the per-sample sink (its latency resolution)
ONSET_ROWS = 25  # estimates after each drop onset counted as the onset burst (fall time ~2 ms + 0.5 ms)


@dataclass(frozen=True)
class Case:
    kind: str  # per_sample | batched
    executor: str  # events | single
    rate: float  # samples/s
    signal: str = "cycle"  # cycle (drops, EKF on 80 % of samples) | levitated (no drop: no EKF)
    output: str = ""  # per_sample | batch; default: the input's kind

    @property
    def output_mode(self) -> str:
        return self.output or ("batch" if self.kind == "batched" else "per_sample")


# ------------------------------------------------------------------------------------------- signal
def drop_cycle(sample_period: float, seed: int = 0, signal: str = "cycle", cycle_seconds: float = 0.0) -> np.ndarray:
    """One cycle of displacements (n, 3) m: levitated, the core model's drop, ramp back, levitated.

    signal "levitated": the same length of levitation only (the EKF never runs). cycle_seconds: a
    longer cycle, levitated after the drop (a drop every cycle_seconds s); 0: the 0.2 s cycle.
    """
    import jax
    import jax.numpy as jnp

    from touchdown_ros.core.dynamics import rk4_step
    from touchdown_ros.io.config import load_config

    config = load_config()
    model = config.model()
    substeps = 10
    h = sample_period / substeps
    n = lambda seconds: int(round(seconds / sample_period))  # noqa: E731
    xi0 = jnp.zeros(model.law.state_size).at[4].set(0.005)  # a spinning ring (8 states) at rest at the drop

    def per_sample(xi, _):
        xi = jax.lax.fori_loop(0, substeps, lambda i, s: rk4_step(model, s, h), xi)
        return xi, xi

    _, states = jax.jit(lambda x: jax.lax.scan(per_sample, x, None, length=n(0.15)))(xi0)
    drop = np.asarray(states)[:, :3]
    ramp = np.linspace(drop[-1], np.zeros(3), n(0.005))
    after = max(n(0.025), n(cycle_seconds) - n(LEVITATED_BEFORE_DROP) - len(drop) - len(ramp))
    positions = np.concatenate([np.zeros((n(LEVITATED_BEFORE_DROP), 3)), drop, ramp, np.zeros((after, 3))])
    if signal == "levitated":
        positions = np.zeros_like(positions)
    return positions + config.noise_rms * np.random.default_rng(seed).standard_normal(positions.shape)


# ------------------------------------------------------------------------------------------- publisher role
def publisher_main(args: argparse.Namespace) -> int:
    """Publish the cycle at args.rate for args.duration s, stamped with the wall clock; print JSON."""
    import rclpy
    from geometry_msgs.msg import PointStamped
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    from touchdown_ros.ros import messages

    if args.publisher_priority:  # the AMB controller / sensor driver it stands for runs real-time
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.publisher_priority))
    period = 1.0 / args.rate
    cycle = drop_cycle(period, signal=args.signal, cycle_seconds=getattr(args, "cycle_seconds", 0.0))
    rclpy.init()
    node = rclpy.create_node("bench_publisher")
    profile = QoSProfile(depth=10000, reliability=ReliabilityPolicy.RELIABLE)
    batched = args.kind == "batched"
    topic = "/amb/displacement_batch" if batched else "/amb/displacement"
    publisher = node.create_publisher(PointCloud2 if batched else PointStamped, topic, profile)
    deadline = time.monotonic() + 60
    while publisher.get_subscription_count() == 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(1.0)
    total = int(round(args.duration * args.rate))
    period_ns = int(round(period * 1e9))
    start_ns = time.time_ns()
    start = time.perf_counter()
    cpu0 = time.process_time()
    sent = 0
    unit = BATCH if batched else 1
    late = []  # per sample: sent (after its publish call) - stamp, ns
    while sent < total:
        due = min(total, int((time.perf_counter() - start) * args.rate) // unit * unit)
        if due >= sent + unit or due == total and due > sent:
            index = np.arange(sent, due)
            stamps = start_ns + index * period_ns
            xyz = cycle[index % len(cycle)]
            if batched:
                for a in range(0, len(index), BATCH):
                    publisher.publish(messages.batch_cloud(int(stamps[a]), "amb_sensor", stamps[a:a + BATCH],
                                                           xyz[a:a + BATCH]))
            else:
                for blob in messages.encode_stamped("PointStamped", stamps, xyz, None, "amb_sensor"):
                    publisher.publish(blob)
            late.append(time.time_ns() - stamps)
            sent = due
        else:
            time.sleep(0.0002)
    seconds = time.perf_counter() - start
    late_ms = np.concatenate(late) / 1e6
    print(json.dumps({"sent": sent, "seconds": seconds, "cpu": time.process_time() - cpu0, "start_ns": start_ns,
                      "period_ns": period_ns, "cycle": len(cycle), "late_p50_ms": float(np.percentile(late_ms, 50)),
                      "late_p99_ms": float(np.percentile(late_ms, 99)), "late_max_ms": float(late_ms.max()),
                      "largest_burst": int(max(len(block) for block in late))}), flush=True)
    time.sleep(1.0)
    node.destroy_node()
    rclpy.shutdown()
    return 0


# ------------------------------------------------------------------------------------------- orchestrator
def shut_down(node: subprocess.Popen, executor, peer, context, log) -> None:
    """Stop the node process (SIGINT, then kill after 10 s), the peer's executor, node and context, and close
    the log."""
    import rclpy

    if node.poll() is None:
        node.send_signal(signal.SIGINT)
        try:
            node.wait(timeout=10)
        except subprocess.TimeoutExpired:
            node.kill()
    executor.shutdown()
    peer.destroy_node()
    rclpy.shutdown(context=context)
    log.close()


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def run_case(case: Case, duration: float, domain: int, params: list[str] = (), publisher_priority: int = 0,
             stall: float = 0.0) -> dict:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import WrenchStamped
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    from touchdown_ros.ros import messages
    from touchdown_ros.ros.runtime import DrainedSubscription

    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    env.pop("ROS_LOCALHOST_ONLY", None)
    os.environ.update(ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    batched_output = case.output_mode == "batch"
    node_args = ["-p", f"node.executor:={case.executor}", "-p", f"sensor.sample_period:={1.0 / case.rate!r}",
                 "-p", f"node.output_mode:={case.output_mode}"]
    for param in params:
        node_args += ["-p", param]
    log_path = Path(tempfile.gettempdir()) / f"touchdown_bench_node_{case.kind}_{case.executor}_{int(case.rate)}.log"
    log = open(log_path, "w")  # the node's log, for when a case fails
    node = subprocess.Popen([sys.executable, "-m", "touchdown_ros.ros.node", "--ros-args", *node_args],
                            env=env, stdout=log, stderr=subprocess.STDOUT)
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain)
    peer = rclpy.create_node("bench_sink", context=context)
    from rclpy.experimental import EventsExecutor

    executor = EventsExecutor(context=context)  # SingleThreadedExecutor cannot take 10 kHz itself
    executor.add_node(peer)
    latencies = array.array("q")
    latency_stamps = array.array("q")  # the sample stamp of each latency
    diagnostics: dict[str, dict[str, str]] = {}
    worst_p99 = [0.0, 0.0]  # node: stamp -> published, arrival -> published (worst 1 s period)

    def on_wrench(data: bytes, now: int) -> None:
        sec, nanosec = struct.unpack_from("<iI", data, 4)
        latencies.append(now - (sec * 1_000_000_000 + nanosec))
        latency_stamps.append(sec * 1_000_000_000 + nanosec)

    def drain_wrenches(subscription: DrainedSubscription, stop: threading.Event) -> None:
        """The per-sample sink: takes what waits every SINK_POLL s (cheaper than a callback per message)."""
        while not stop.is_set():
            for data in subscription.take(10000):
                on_wrench(data, time.time_ns())
            time.sleep(SINK_POLL)

    def on_batch(message: PointCloud2) -> None:
        now = time.time_ns()
        t = messages.cloud_columns(message, ("t",))[:, 0]
        stamps = messages.stamp_ns_of(message.header.stamp) + np.rint(t * 1e9).astype(np.int64)
        latencies.extend((now - stamps).tolist())
        latency_stamps.extend(stamps.tolist())

    def on_diagnostics(message: DiagnosticArray) -> None:
        for status in message.status:
            values = messages.status_values(status)
            diagnostics[status.name] = values
            if status.name.endswith("filter") and values.get("latency_p99_ms", "nan") != "nan":
                worst_p99[0] = max(worst_p99[0], float(values["latency_p99_ms"]))
                worst_p99[1] = max(worst_p99[1], float(values.get("in_node_p99_ms", "nan")))

    # A monitoring consumer. Per sample: best effort (a reliable reader costs the node ~5 us more per
    # message), drained by a thread like the node's input; batched: reliable (one message per EKF run,
    # large when the node is behind).
    sink_qos = QoSProfile(depth=10000, reliability=ReliabilityPolicy.BEST_EFFORT)
    stop_sink = threading.Event()
    sink = None
    if batched_output:
        reliable = QoSProfile(depth=10000, reliability=ReliabilityPolicy.RELIABLE)
        peer.create_subscription(PointCloud2, "/touchdown/estimate_batch", on_batch, reliable)
    else:
        wrenches = DrainedSubscription(peer, WrenchStamped, "/touchdown/contact_force", sink_qos)
        sink = threading.Thread(target=drain_wrenches, args=(wrenches, stop_sink), daemon=True)
        sink.start()
    peer.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 100)

    never = rclpy.task.Future()

    def spin_until(condition, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and not condition():
            executor.spin_until_future_complete(never, timeout_sec=0.05)
        return condition()

    try:
        if not spin_until(lambda: "touchdown_estimator: model" in diagnostics or node.poll() is not None, 300):
            raise RuntimeError("node did not start")
        publisher = subprocess.Popen(
            [sys.executable, __file__, "--role", "publisher", "--kind", case.kind, "--rate", str(case.rate),
             "--duration", str(duration), "--signal", case.signal, "--publisher-priority", str(publisher_priority)],
            env=env, stdout=subprocess.PIPE, text=True,
        )
        received = lambda: int(diagnostics.get("touchdown_estimator: input", {}).get("received", -1))  # noqa: E731
        spin_until(lambda: received() > 0 or publisher.poll() is not None, 120)
        cpu_start, wall_start, own_cpu_start = cpu_seconds(node.pid), time.monotonic(), time.process_time()
        worst_p99[:] = [0.0, 0.0]
        if stall:  # the whole node process stopped for `stall` s halfway, as a VM or machine hiccup would
            spin_until(lambda: publisher.poll() is not None, duration / 2)
            os.kill(node.pid, signal.SIGSTOP)
            time.sleep(stall)
            os.kill(node.pid, signal.SIGCONT)
        spin_until(lambda: publisher.poll() is not None, duration + 120)
        cpu_node = cpu_seconds(node.pid) - cpu_start
        wall = time.monotonic() - wall_start
        cpu_own = time.process_time() - own_cpu_start
        report = json.loads(publisher.stdout.read().strip().splitlines()[-1])
        sent = report["sent"]
        # Let the node work off a backlog: until it has everything or makes no progress for 3 s.
        catch_up_start, last, last_change = time.monotonic(), received(), time.monotonic()
        while received() < sent and time.monotonic() - last_change < 3.0 and time.monotonic() - catch_up_start < 300:
            spin_until(lambda: False, 0.5)
            if received() != last:
                last, last_change = received(), time.monotonic()
        behind_s = time.monotonic() - catch_up_start if received() >= sent else float("inf")
        spin_until(lambda: False, 2.0)  # the last estimates and diagnostics
        counts = diagnostics.get("touchdown_estimator: input", {})
        lat_ms = np.frombuffer(latencies, dtype=np.int64) / 1e6
        # The first ONSET_ROWS estimates of each drop are late by construction: the drop is only known when
        # z has fallen drop_detection.threshold (~2 ms of free fall). Their share of the tail, shown apart:
        index = (np.frombuffer(latency_stamps, dtype=np.int64) - report["start_ns"]) // report["period_ns"]
        onset = index % report["cycle"] - round(LEVITATED_BEFORE_DROP * case.rate)
        burst = (onset >= 0) & (onset < ONSET_ROWS)
        return {
            "case": case,
            "sent": sent,
            "publish_seconds": report["seconds"],
            "received": received(),
            "catch_up_s": behind_s,
            "gaps": int(counts.get("gaps", -1)),
            "missing": int(counts.get("missing_samples", -1)),
            "estimated": int(diagnostics.get("touchdown_estimator: filter", {}).get("estimated", -1)),
            "estimates_received": len(latencies),
            "p50_ms": float(np.percentile(lat_ms, 50)) if lat_ms.size else float("nan"),
            "p99_ms": float(np.percentile(lat_ms, 99)) if lat_ms.size else float("nan"),
            "max_ms": float(np.max(lat_ms)) if lat_ms.size else float("nan"),
            "onset_share": float(np.mean(burst)) if lat_ms.size else float("nan"),
            "p99_without_onset_ms": float(np.percentile(lat_ms[~burst], 99)) if (~burst).any() else float("nan"),
            "p99_onset_ms": float(np.percentile(lat_ms[burst], 99)) if burst.any() else float("nan"),
            "node_p50_ms": float(diagnostics.get("touchdown_estimator: filter", {}).get("latency_total_p50_ms", "nan")),
            "node_p99_ms": float(diagnostics.get("touchdown_estimator: filter", {}).get("latency_total_p99_ms", "nan")),
            "node_worst_p99_ms": worst_p99[0],
            "in_node_worst_p99_ms": worst_p99[1],
            "node_cpu_pct": 100.0 * cpu_node / wall,
            "subscriber_cpu_pct": 100.0 * cpu_own / wall,
            "publisher_cpu_pct": 100.0 * report["cpu"] / report["seconds"],
            "publisher_late_p50_ms": report["late_p50_ms"],
            "publisher_late_p99_ms": report["late_p99_ms"],
            "publisher_late_max_ms": report["late_max_ms"],
            "publisher_largest_burst": report["largest_burst"],  # most samples sent at one wake-up
        }
    finally:
        stop_sink.set()
        if sink is not None:
            sink.join(timeout=5)
        shut_down(node, executor, peer, context, log)


def _ms(value: float) -> str:
    return "> 1000" if value >= 1000.0 else f"{value:.2f}"


def table(results: list[dict]) -> str:
    rows = [
        "| input | output | executor | signal | rate (samples/s) | sent | lost | behind at the end (s) "
        "| stamp -> published p50 / p99 (ms) | stamp -> received by a subscriber p50 / p99 (ms) "
        "| received p99: without the onset burst / burst (ms) | estimates received | node CPU (% of a core) "
        "| publisher: stamp -> sent p50 / p99 (ms), CPU (%) | subscriber CPU (%) |",
        "|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in results:
        c = r["case"]
        lost = r["sent"] - r["received"]
        behind = "-" if r["catch_up_s"] < 0.6 else f"{r['catch_up_s']:.0f}"
        rows.append(
            f"| {c.kind.replace('_', '-')} | {c.output_mode.replace('_', '-')} | {c.executor} | {c.signal} "
            f"| {c.rate:,.0f} | {r['sent']:,} | {lost:,} "
            f"| {behind} | {_ms(r['node_p50_ms'])} / {_ms(r['node_p99_ms'])} "
            f"| {_ms(r['p50_ms'])} / {_ms(r['p99_ms'])} "
            f"| {_ms(r['p99_without_onset_ms'])} / {_ms(r['p99_onset_ms'])} "
            f"| {r['estimates_received']:,} of {r['estimated']:,} | {r['node_cpu_pct']:.0f} "
            f"| {_ms(r['publisher_late_p50_ms'])} / {_ms(r['publisher_late_p99_ms'])}, {r['publisher_cpu_pct']:.0f} "
            f"| {r['subscriber_cpu_pct']:.0f} |"
        )
    return "\n".join(rows)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--role", choices=("bench", "publisher"), default="bench")
    parser.add_argument("--kind", choices=("per_sample", "batched"), default="per_sample")
    parser.add_argument("--rate", type=float, default=10000.0)
    parser.add_argument("--signal", choices=("cycle", "levitated"), default="cycle")
    parser.add_argument("--duration", type=float, default=60.0, help="s of publishing per case (default 60)")
    parser.add_argument("--cycle-seconds", type=float, default=0.0,
                        help="publisher: a drop every this many s (levitated in between); default 0: every 0.2 s")
    parser.add_argument("--param", action="append", default=[], metavar="NAME:=VALUE",
                        help="extra node parameter for every case, e.g. node.receive:=callback")
    parser.add_argument("--publisher-priority", type=int, default=0, metavar="P",
                        help="run the publisher at SCHED_FIFO priority P, as the AMB controller it stands for "
                             "(with -p node.realtime_priority:=N, N < P); default 0: normal scheduling")
    parser.add_argument("--stall", type=float, default=0.0, metavar="S",
                        help="stop the node process (SIGSTOP) for S s halfway through each case, then continue it")
    parser.add_argument("--busy-loops", type=int, default=0, metavar="N",
                        help="N Python busy loops at normal priority beside every case: other load on the machine")
    parser.add_argument("--cases", nargs="*", metavar="KIND:EXECUTOR:RATE[:SIGNAL[:OUTPUT]]",
                        help="e.g. per_sample:events:10000 batched:events:100000:levitated "
                             "per_sample:events:10000:cycle:batch (per-sample input, batched output)")
    args = parser.parse_args()
    if args.role == "publisher":
        return publisher_main(args)
    specs = args.cases or [
        "per_sample:events:10000", "per_sample:events:10000:cycle:batch", "per_sample:single:10000",
        "batched:events:100000", "batched:events:40000",
        "batched:events:100000:levitated", "batched:single:100000:levitated",
    ]
    cases = []
    for spec in specs:
        kind, executor, rate, *rest = spec.split(":")
        cases.append(Case(kind, executor, float(rate), *rest))
    results = []
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.busy_loops)]
    try:
        for i, case in enumerate(cases):
            print(f"running {case} for {args.duration:.0f} s ...", file=sys.stderr, flush=True)
            result = run_case(case, args.duration, domain=60 + i, params=args.param,
                              publisher_priority=args.publisher_priority, stall=args.stall)
            print(f"  {result}", file=sys.stderr, flush=True)
            results.append(result)
    finally:
        for loop in busy:
            loop.kill()
            loop.wait()
    load = os.getloadavg()[0]
    extra = f", node parameters {' '.join(args.param)}" if args.param else ""
    if args.publisher_priority:
        extra += f", publisher at SCHED_FIFO {args.publisher_priority}"
    if args.busy_loops:
        extra += f", {args.busy_loops} busy loop(s) at normal priority beside it"
    if args.stall:
        extra += f", node stopped for {args.stall:g} s halfway"
    print(f"\nMeasured {time.strftime('%Y-%m-%d')} on {os.cpu_count()} cores (load average {load:.1f} at the end), "
          f"{args.duration:.0f} s per case{extra}.\n")
    print(table(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
