"""Soak of the live node: 10 kHz per-sample input with a drop every few seconds, for a long time.

Starts `touchdown_estimator` in its own process, publishes from a second process (the
publisher role of bench/node_throughput.py, stamped with the wall clock) a cycle of
`--cycle-seconds` s: 20 ms levitated, the core model's 150 ms drop, 5 ms back, then
levitated to the end of the cycle, and in this process follows the node's /diagnostics
and its memory. Reports:

* samples lost: sent against received by the node (its `input` counts), and the gaps it saw;
* latency from sample stamp to published estimate: the node's p99 over the whole run
  (its histogram) and the worst and median of the per-period p99;
* the node's resident memory (VmRSS of /proc/PID/status) every `--rss-every` s, and its
  drift: the last tenth of the run against the first tenth after the warm-up (the first
  `--warm-up` s are left out: JAX compiles and caches fill then);
* drops and re-levitations the node counted against the cycles sent.

Runs outside CI (default 1 h). Run: .venv/bin/python bench/node_soak.py [--duration 3600]
[--cycle-seconds 3] [--param node.realtime_priority:=10 --publisher-priority 20].
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from node_throughput import cpu_seconds, shut_down  # noqa: E402

THROUGHPUT = Path(__file__).parent / "node_throughput.py"


def rss_mib(pid: int) -> float:
    """Resident memory of a process, MiB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def soak(duration: float, rate: float, cycle_seconds: float, params: list[str], publisher_priority: int,
         rss_every: float, warm_up: float, domain: int) -> dict:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.experimental import EventsExecutor

    from touchdown_ros.ros import messages

    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    env.pop("ROS_LOCALHOST_ONLY", None)
    os.environ.update(ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    node_args = ["-p", f"sensor.sample_period:={1.0 / rate!r}"]
    for param in params:
        node_args += ["-p", param]
    log_path = Path(tempfile.gettempdir()) / "touchdown_soak_node.log"
    log = open(log_path, "w")
    node = subprocess.Popen([sys.executable, "-m", "touchdown_ros.ros.node", "--ros-args", *node_args],
                            env=env, stdout=log, stderr=subprocess.STDOUT)
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain)
    peer = rclpy.create_node("soak_monitor", context=context)
    executor = EventsExecutor(context=context)
    executor.add_node(peer)
    diagnostics: dict[str, dict[str, str]] = {}
    period_p99: list[float] = []

    def on_diagnostics(message: DiagnosticArray) -> None:
        for status in message.status:
            values = messages.status_values(status)
            diagnostics[status.name] = values
            if status.name.endswith("filter") and values.get("latency_p99_ms", "nan") != "nan":
                period_p99.append(float(values["latency_p99_ms"]))

    peer.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 100)
    never = rclpy.task.Future()

    def spin_until(condition, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and not condition():
            executor.spin_until_future_complete(never, timeout_sec=0.05)
        return condition()

    def value(status: str, key: str, default: float = -1) -> float:
        return float(diagnostics.get(f"touchdown_estimator: {status}", {}).get(key, default))

    rss: list[tuple[float, float]] = []  # (s since the first sample, MiB)
    try:
        if not spin_until(lambda: "touchdown_estimator: model" in diagnostics or node.poll() is not None, 300):
            raise RuntimeError(f"node did not start, see {log_path}")
        publisher = subprocess.Popen(
            [sys.executable, str(THROUGHPUT), "--role", "publisher", "--kind", "per_sample", "--rate", str(rate),
             "--duration", str(duration), "--cycle-seconds", str(cycle_seconds),
             "--publisher-priority", str(publisher_priority)],
            env=env, stdout=subprocess.PIPE, text=True,
        )
        spin_until(lambda: value("input", "received") > 0 or publisher.poll() is not None, 120)
        start, cpu_start = time.monotonic(), cpu_seconds(node.pid)
        period_p99.clear()
        next_rss = start
        while publisher.poll() is None:
            now = time.monotonic()
            if now >= next_rss:
                rss.append((now - start, rss_mib(node.pid)))
                next_rss += rss_every
            spin_until(lambda: False, 0.5)
        wall, cpu_node = time.monotonic() - start, cpu_seconds(node.pid) - cpu_start
        report = json.loads(publisher.stdout.read().strip().splitlines()[-1])
        sent = report["sent"]
        spin_until(lambda: value("input", "received") >= sent, 30)
        spin_until(lambda: False, 2.0)
        rss.append((time.monotonic() - start, rss_mib(node.pid)))
        times, mib = np.array(rss).T
        after = times >= warm_up
        steady = mib[after] if after.sum() >= 4 else mib
        tenth = max(1, len(steady) // 10)
        first, last = float(np.mean(steady[:tenth])), float(np.mean(steady[-tenth:]))
        p99s = np.array(period_p99) if period_p99 else np.array([np.nan])
        return {
            "duration_s": wall,
            "rate": rate,
            "cycle_seconds": cycle_seconds,
            "sent": sent,
            "received": int(value("input", "received")),
            "lost": sent - int(value("input", "received")),
            "gaps": int(value("input", "gaps")),
            "missing_samples": int(value("input", "missing_samples")),
            "long_gaps": int(value("input", "long_gaps", 0)),
            "clock_jump_forward": int(value("input", "clock_jump_forward")),
            "cycles_sent": sent // report["cycle"],
            "drops": int(value("contact", "drops")),
            "relevitations": int(value("contact", "relevitations")),
            "node_p50_ms": value("filter", "latency_total_p50_ms", float("nan")),
            "node_p99_ms": value("filter", "latency_total_p99_ms", float("nan")),
            "period_p99_median_ms": float(np.nanmedian(p99s)),
            "period_p99_worst_ms": float(np.nanmax(p99s)),
            "node_cpu_pct": 100.0 * cpu_node / wall,
            "publisher_late_p99_ms": report["late_p99_ms"],
            "rss_mib": [(round(t, 1), round(m, 1)) for t, m in rss],
            "rss_first_tenth_mib": first,
            "rss_last_tenth_mib": last,
            "rss_drift_pct": 100.0 * (last - first) / first,
            "rss_max_mib": float(np.max(mib)),
        }
    finally:
        shut_down(node, executor, peer, context, log)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--duration", type=float, default=3600.0, help="s of publishing (default 3600: 1 h)")
    parser.add_argument("--rate", type=float, default=10000.0, help="samples/s, one PointStamped each (default 10 kHz)")
    parser.add_argument("--cycle-seconds", type=float, default=3.0, help="a drop every this many s (default 3)")
    parser.add_argument("--rss-every", type=float, default=10.0, help="s between two readings of the node's RSS")
    parser.add_argument("--warm-up", type=float, default=30.0, help="s left out of the RSS drift (default 30)")
    parser.add_argument("--param", action="append", default=[], metavar="NAME:=VALUE", help="extra node parameter")
    parser.add_argument("--publisher-priority", type=int, default=0, metavar="P",
                        help="publisher at SCHED_FIFO P (with --param node.realtime_priority:=N, N < P)")
    parser.add_argument("--domain", type=int, default=77, help="ROS_DOMAIN_ID of the run")
    args = parser.parse_args()
    result = soak(args.duration, args.rate, args.cycle_seconds, args.param, args.publisher_priority,
                  args.rss_every, args.warm_up, args.domain)
    print(json.dumps(result, indent=1), file=sys.stderr)
    r = result
    print(f"\nSoak {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {os.cpu_count()} cores, load average "
          f"{os.getloadavg()[0]:.1f} at the end, {r['duration_s']:.0f} s at {r['rate']:,.0f} samples/s per sample, "
          f"a drop every {r['cycle_seconds']:g} s{', ' + ' '.join(args.param) if args.param else ''}:\n")
    print(
        "| sent | lost | holes the node saw: bridged gaps (missing) / long gaps / clock jumps "
        "| drops / relevitations (cycles sent) | stamp -> published p50 / p99 (ms, "
        "whole run) | per-period p99 median / worst (ms) | node CPU (%) | RSS after warm-up, first / last tenth "
        "(MiB) | RSS drift | RSS max (MiB) |"
    )
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    print(f"| {r['sent']:,} | {r['lost']:,} | {r['gaps']} ({r['missing_samples']}) / {r['long_gaps']} / "
          f"{r['clock_jump_forward']} | {r['drops']} / "
          f"{r['relevitations']} ({r['cycles_sent']}) | {r['node_p50_ms']:.2f} / {r['node_p99_ms']:.2f} | "
          f"{r['period_p99_median_ms']:.2f} / {r['period_p99_worst_ms']:.2f} | {r['node_cpu_pct']:.0f} | "
          f"{r['rss_first_tenth_mib']:.1f} / {r['rss_last_tenth_mib']:.1f} | {r['rss_drift_pct']:+.1f} % | "
          f"{r['rss_max_mib']:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
