"""``stage install-service``: run a show at boot, restarted if it fails (systemd).

    sudo stage install-service --name gallery -- serve --rig /etc/stage/rig.yaml
    stage install-service --user --print -- play /home/me/piece.yaml --midi fluidsynth

writes a systemd unit that runs ``python -m stage COMMAND...`` with the
Python this command runs under (so the same installation), restarts it when
it fails, stops it with SIGTERM (every note is silenced), and sends its log
to the journal (``journalctl -u NAME``), which dates every line. Without
``--print``/``--output`` it installs the unit and enables it now and at boot
(``systemctl [--user] enable --now``). docs/installing.md has the details, a
manual check, and what to do on Windows.
"""

from __future__ import annotations

import argparse
import getpass
import os
import shutil
import subprocess
import sys
from pathlib import Path

from ..errors import ConfigError
from .common import Exit

#: commands a service makes sense for (they run until stopped)
SERVICE_COMMANDS = ("serve", "play", "monitor", "record", "client", "sim", "replay", "demo")


def register(sub) -> dict:
    p = sub.add_parser("install-service",
                       help="run a show at boot with systemd, restarted if it fails",
                       description="Write (and install and enable) a systemd unit that runs "
                       "`stage COMMAND ARGS...` at boot and restarts it when it fails. Put the "
                       "stage command after `--`.")
    p.add_argument("--name", default="stage", help="unit name (default: stage)")
    p.add_argument("--user", action="store_true",
                   help="a user unit (~/.config/systemd/user): sound servers (JACK, PipeWire) "
                        "run in the user's session; see docs/installing.md for starting at boot")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--print", action="store_true", help="print the unit, install nothing")
    where.add_argument("--output", metavar="FILE", help="write the unit here, install nothing")
    p.add_argument("--no-enable", action="store_true",
                   help="install the unit but do not enable or start it")
    p.add_argument("--working-dir", metavar="DIR", default=None,
                   help="folder the show runs in (default: the current one)")
    p.add_argument("--restart-sec", type=float, default=5.0, metavar="S",
                   help="wait S seconds before a restart (default 5)")
    p.add_argument("show", nargs=argparse.REMAINDER, metavar="-- COMMAND ARGS",
                   help="the stage command to run, e.g. -- serve --rig rig.yaml")
    return {"install-service": cmd_install_service}


def _quote(arg: str) -> str:
    """One ExecStart word, quoted for systemd (systemd.syntax(7), systemd.service(5))."""
    arg = arg.replace("%", "%%").replace("$", "$$")
    if arg and not any(c in arg for c in ' \t\n"\'\\;'):
        return arg
    return '"' + arg.replace("\\", "\\\\").replace('"', '\\"') + '"'


def unit_text(args: list[str], name: str, user: bool, working_dir: str,
              restart_sec: float = 5.0, python: str | None = None,
              run_as: str | None = None) -> str:
    """The unit file for ``stage ARGS`` (see the module docstring)."""
    if not args:
        raise ConfigError("give the stage command to run after --, e.g. "
                          "stage install-service -- serve --rig rig.yaml")
    if args[0] not in SERVICE_COMMANDS:
        raise ConfigError(f"'{args[0]}' is not a command to run as a service; one of: "
                          + ", ".join(SERVICE_COMMANDS))
    python = python or sys.executable
    exec_start = " ".join(_quote(a) for a in [python, "-m", "stage", *args])
    lines = [
        "# Written by `stage install-service`; see docs/installing.md",
        "[Unit]",
        f"Description=stage {args[0]} ({name})",
        "Wants=network-online.target",
        "After=network-online.target sound.target",
        "# give up restarting only after 10 failures within 10 minutes",
        "StartLimitIntervalSec=600",
        "StartLimitBurst=10",
        "",
        "[Service]",
        "Type=simple",
        f"ExecStart={exec_start}",
        f"WorkingDirectory={_quote(working_dir)}",
        "Restart=on-failure",
        f"RestartSec={restart_sec:g}",
        "# SIGTERM stops the show cleanly (every note silenced); it then exits 130",
        "KillSignal=SIGTERM",
        "TimeoutStopSec=20",
        "SuccessExitStatus=130",
        "# the journal dates every line: journalctl -u " + name,
        "Environment=PYTHONUNBUFFERED=1",
    ]
    if run_as and not user:
        lines.append(f"User={run_as}")
    lines += ["", "[Install]", f"WantedBy={'default.target' if user else 'multi-user.target'}",
              ""]
    return "\n".join(lines)


def cmd_install_service(args: argparse.Namespace) -> int:
    show = list(args.show)
    if show and show[0] == "--":
        show = show[1:]
    if not args.name.replace("-", "").replace("_", "").replace("@", "").isalnum():
        raise ConfigError(f"--name {args.name}: use letters, digits, - and _ only")
    working = os.path.abspath(args.working_dir or os.getcwd())
    # a system unit for root would run the show as root: run it as the user who asked
    # (sudo keeps them in SUDO_USER), so files it writes stay theirs
    run_as = None if args.user else (os.environ.get("SUDO_USER") or None)
    text = unit_text(show, args.name, args.user, working, args.restart_sec, run_as=run_as)
    if args.print:
        sys.stdout.write(text)
        return Exit.OK
    if args.output:
        Path(args.output).write_text(text, encoding="utf-8")
        print(f"stage: unit written to {args.output}")
        return Exit.OK
    if args.user:
        folder = Path(os.environ.get("XDG_CONFIG_HOME") or Path.home() / ".config") / \
            "systemd" / "user"
    else:
        folder = Path("/etc/systemd/system")
    path = folder / f"{args.name}.service"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
    except OSError as exc:
        hint = "" if args.user else " (a system unit needs root: sudo, or --user)"
        raise ConfigError(f"cannot write {path}: {exc.strerror}{hint}") from None
    print(f"stage: unit written to {path}")
    systemctl = shutil.which("systemctl")
    scope = ["--user"] if args.user else []
    steps = [[*scope, "daemon-reload"]]
    if not args.no_enable:
        steps.append([*scope, "enable", "--now", f"{args.name}.service"])
    manual = "; ".join("systemctl " + " ".join(s) for s in steps)
    if systemctl is None:
        print(f"stage: systemctl not found: run, where systemd runs: {manual}", file=sys.stderr)
        return Exit.FAILURE
    for step in steps:
        done = subprocess.run([systemctl, *step], capture_output=True, text=True)
        if done.returncode != 0:
            why = (done.stderr or done.stdout).strip().splitlines()
            print(f"stage: systemctl {' '.join(step)} failed: {why[-1] if why else done.returncode}"
                  f"; the unit is written, run by hand: {manual}", file=sys.stderr)
            return Exit.FAILURE
    user = getpass.getuser()
    print(f"stage: {args.name} enabled and started; logs: journalctl "
          f"{'--user ' if args.user else ''}-u {args.name} -f"
          + (f" (for it to start at boot without a login: loginctl enable-linger {user})"
             if args.user else ""))
    return Exit.OK
