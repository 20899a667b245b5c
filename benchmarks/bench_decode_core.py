"""Pure-decoder throughput on random logits (no model): offline DP, online decoder, reference-style DP.

Run: .venv/bin/python benchmarks/bench_decode_core.py [--max-len 25] [--seed 0]
Prints steps/s (best of a few repeats) and the online decoder's commit latency.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from playseg_core.ps.decoding import (
    OnlineDecoder,
    decode_segments,
    end_columns,
    segment_log_scores,
)
from playseg_core.ps.reference_style import reference_style_decode


@dataclass
class BenchConfig:
    max_len: int = 25
    seed: int = 0
    offline_steps: tuple[int, ...] = (50, 1000, 100_000)
    online_steps: tuple[int, ...] = (1000, 100_000)
    reference_steps: tuple[int, ...] = (50, 100, 150, 200)


def random_logits(num_steps: int, max_len: int, rng: np.random.Generator) -> np.ndarray:
    """Noisy logits with one likely end per start, like a trained model on play data."""
    logits = rng.normal(-3.0, 2.0, size=(num_steps, max_len))
    logits[np.arange(num_steps), rng.integers(0, max_len, size=num_steps)] += 6.0
    return logits


def confident_logits(num_steps: int, max_len: int, rng: np.random.Generator) -> np.ndarray:
    """A confident model: +8 where a hidden true segmentation (lengths 2..max_len-4) ends, -8 elsewhere."""
    logits = rng.normal(-8.0, 1.0, size=(num_steps, max_len))
    start = 0
    while start < num_steps:
        length = min(int(rng.integers(2, max_len - 3)), num_steps - start)
        logits[start, length - 1] += 16.0
        start += length
    return logits


def best_time(run: Callable[[], object], repeats: int) -> float:
    """Fastest of ``repeats`` wall-clock runs, in seconds."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    return min(times)


def run_online(columns: np.ndarray, max_len: int) -> OnlineDecoder:
    decoder = OnlineDecoder(max_len=max_len)
    for column in columns:
        decoder.push(column)
    decoder.finish()
    return decoder


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--max-len", type=int, default=BenchConfig.max_len)
    parser.add_argument("--seed", type=int, default=BenchConfig.seed)
    args = parser.parse_args()
    config = BenchConfig(max_len=args.max_len, seed=args.seed)
    rng = np.random.default_rng(config.seed)
    max_len = config.max_len

    print(f"offline decode_segments, max_len={max_len}, min_len=1")
    print(f"{'T':>8} {'scores ms':>10} {'decode ms (incl. scores)':>25} {'steps/s':>12}")
    for num_steps in config.offline_steps:
        logits = random_logits(num_steps, max_len, rng)
        repeats = 5 if num_steps <= 1000 else 2
        scores_s = best_time(lambda logits=logits: segment_log_scores(logits), repeats)
        decode_s = best_time(lambda logits=logits: decode_segments(logits), repeats)
        print(
            f"{num_steps:>8} {scores_s * 1e3:>10.2f} {decode_s * 1e3:>25.2f} {num_steps / decode_s:>12,.0f}"
        )

    print(f"\nOnlineDecoder (push per step + finish), max_len={max_len}")
    print(
        f"{'logits':>9} {'T':>8} {'total ms':>10} {'steps/s':>10} {'us/push':>8} "
        f"{'latency mean':>13} {'p95':>5} {'max':>5}"
    )
    for kind, make in (("noisy", random_logits), ("confident", confident_logits)):
        for num_steps in config.online_steps:
            logits = make(num_steps, max_len, rng)
            columns = end_columns(logits)
            start = time.perf_counter()
            decoder = run_online(columns, max_len)
            elapsed = time.perf_counter() - start
            if [(c.start, c.end) for c in decoder.commits] != decode_segments(logits).segments:
                raise RuntimeError("online and offline segmentations differ")
            latency = np.array([c.latency for c in decoder.commits])
            print(
                f"{kind:>9} {num_steps:>8} {elapsed * 1e3:>10.1f} {num_steps / elapsed:>10,.0f} "
                f"{elapsed / num_steps * 1e6:>8.1f} {latency.mean():>13.2f} "
                f"{np.percentile(latency, 95):>5.0f} {latency.max():>5d}"
            )

    print(
        "latency = steps from a boundary to the push that commits it; with min_len=1 it is at least "
        "max_len-1 (a later segment may still start at any of the last max_len positions)"
    )

    print(f"\nreference-style DP over (segments, end), Python loops, max_len={max_len} (score lookup only)")
    print(f"{'T':>8} {'reference ms':>13} {'decode_segments ms':>19} {'speed-up':>9}")
    for num_steps in config.reference_steps:
        logits = random_logits(num_steps, max_len, rng)
        scores = segment_log_scores(logits)

        def score_segment(i: int, j: int, scores: np.ndarray = scores) -> float:
            return float(scores[i, j - i - 1])

        reference_s = best_time(
            lambda n=num_steps, f=score_segment: reference_style_decode(f, n, 1, max_len), 1
        )
        decode_s = best_time(lambda logits=logits: decode_segments(logits), 5)
        same = reference_style_decode(score_segment, num_steps, 1, max_len).segments == (
            decode_segments(logits).segments
        )
        if not same:
            raise RuntimeError("reference-style and exact decoding differ")
        print(
            f"{num_steps:>8} {reference_s * 1e3:>13.1f} {decode_s * 1e3:>19.2f} {reference_s / decode_s:>8.0f}x"
        )


if __name__ == "__main__":
    main()
