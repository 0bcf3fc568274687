"""A long fuzzing run of the decoder and the engine (hypothesis); reports inputs tried.

The same properties as tests/test_fuzz.py (stage/testing/fuzz.py), run for
a time budget instead of a few hundred examples:

- the decoder: no exception escapes; every message of a well-formed datagram
  is decoded or dropped with a documented reason; a malformed one is one drop;
- the engine (dispatcher, registry, fusion, output): no exception escapes
  (no internal_error drop), bounded tables, tracks and persons that agree,
  finite joints, and every message handed to it applied or counted.

    python bench/fuzz.py                 # 10 minutes: 8 for the decoder, 2 for the engine
    python bench/fuzz.py --seconds 60
    python bench/fuzz.py --quick         # 20 s

Prints the number of inputs tried, how many were rejected by hypothesis's
own filters, failures (with the smallest failing input), and inputs per
second; exits 1 when a property failed.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time

from hypothesis import HealthCheck, Phase, given, settings, strategies as st

from stage.testing.fuzz import EngineUnderTest, check_decoder, datagrams

SOURCES = [("127.0.0.1", 5000), ("127.0.0.1", 5001), ("127.0.0.2", 5000), ("10.0.0.1", 7000)]


def run(name: str, strategy, prop, budget_s: float) -> dict:
    """Check ``prop`` on inputs drawn from ``strategy`` until ``budget_s`` has passed."""
    tried = {"n": 0, "failed": None}
    deadline = time.monotonic() + budget_s
    started = time.monotonic()
    rounds = 0
    while time.monotonic() < deadline:
        rounds += 1

        @settings(max_examples=250, deadline=None, database=None,
                  phases=[Phase.generate, Phase.shrink], suppress_health_check=list(HealthCheck))
        @given(strategy)
        def one(value) -> None:
            tried["n"] += 1
            prop(value)
        try:
            one()
        except Exception as exc:  # a property failed: hypothesis printed the shrunk input
            tried["failed"] = f"{type(exc).__name__}: {exc}"[:2000]
            break
    elapsed = time.monotonic() - started
    return {"name": name, "inputs": tried["n"], "seconds": round(elapsed, 1),
            "per_s": round(tried["n"] / elapsed, 1) if elapsed else 0.0, "rounds": rounds,
            "failed": tried["failed"]}


def engine(steps) -> None:
    sut = EngineUnderTest()
    for data, source, dt in steps:
        sut.feed(data, source, dt)
        sut.check()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=600.0, help="total budget (default 600)")
    parser.add_argument("--quick", action="store_true", help="20 s in all")
    args = parser.parse_args()
    total = 20.0 if args.quick else args.seconds
    logging.disable(logging.CRITICAL)  # millions of bad inputs: their log lines are not the point
    print(f"fuzzing for {total:.0f} s (hypothesis; decoder 80 %, engine 20 %)", flush=True)
    results = [run("decoder (decode_datagram)", st.one_of(datagrams(), st.binary(max_size=256)),
                   check_decoder, 0.8 * total),
               run("engine (sequences of up to 40 datagrams, checked after each)",
                   st.lists(st.tuples(datagrams(), st.sampled_from(SOURCES),
                                      st.sampled_from([0.0, 0.001, 0.033, 0.5, 2.0])),
                            max_size=40), engine, 0.2 * total)]
    failed = False
    for r in results:
        print(f"{r['name']}: {r['inputs']} inputs tried in {r['seconds']} s "
              f"({r['per_s']}/s, {r['rounds']} hypothesis runs); "
              + ("all properties held" if r["failed"] is None else f"FAILED: {r['failed']}"))
        failed |= r["failed"] is not None
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
