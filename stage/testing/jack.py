"""Running a JACK server from a script (tests, benchmarks, headless installations).

On a machine with no sound card, ``jackd --no-realtime -d dummy`` gives the MIDI
view a JACK graph to publish its port in.
"""

from __future__ import annotations

import os
import subprocess
import threading
import time
from typing import IO


def start_dummy_jackd(name: str, period: int = 256, rate: int = 48000,
                      log: IO | int = subprocess.DEVNULL, timeout: float = 10.0,
                      ) -> subprocess.Popen:
    """Start a named JACK server on the dummy driver and wait until it answers.

    Raises RuntimeError (with the process killed) if it does not come up in ``timeout`` s.
    """
    env = dict(os.environ, JACK_DEFAULT_SERVER=name)
    proc = subprocess.Popen(["jackd", "-n", name, "--no-realtime", "-d", "dummy", "-r",
                             str(rate), "-p", str(period)], stdout=log, stderr=log, env=env)
    deadline = time.monotonic() + timeout
    while subprocess.run(["jack_lsp"], capture_output=True, env=env).returncode != 0:
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            proc.wait(5)
            raise RuntimeError(f"jackd '{name}' did not start")
        time.sleep(0.05)
    return proc


def stop_jackd(proc: subprocess.Popen) -> None:
    """Stop a jackd cleanly unregistered.

    jackd often ignores the first SIGTERM once clients have come and gone (it hangs in
    its shutdown); a few more get it out. Killing it instead would leave its entry in
    JACK's shared registry, which holds only 8 servers.
    """
    for _ in range(20):
        proc.terminate()
        try:
            proc.wait(0.25)
            return
        except subprocess.TimeoutExpired:
            continue
    proc.kill()
    proc.wait(5)


def start_midi_dump(client: str = "dump", timeout: float = 5.0,
                    ) -> tuple[subprocess.Popen, list[str], threading.Thread]:
    """``jack_midi_dump`` as ``client`` on the current JACK server, once its input port is
    registered: the process, its output lines as they come (a thread appends them), and
    that thread, to join once the process has ended (nothing else may read its output).

    Raises RuntimeError (with the process killed) if the port does not appear in time.
    """
    dump = subprocess.Popen(["stdbuf", "-oL", "jack_midi_dump", "-a", client],
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    deadline = time.monotonic() + timeout
    while f"{client}:input" not in subprocess.run(["jack_lsp"], capture_output=True,
                                                  text=True).stdout:
        if time.monotonic() > deadline:
            dump.kill()
            dump.wait(5)
            raise RuntimeError("jack_midi_dump did not register its port")
        time.sleep(0.05)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(dump.stdout), daemon=True)
    reader.start()
    return dump, lines, reader
