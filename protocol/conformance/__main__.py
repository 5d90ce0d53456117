"""``python -m protocol.conformance HOST:PORT [--json]``."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from dataclasses import asdict

from ..constants import DEFAULT_PORT
from . import Target, run_checks


def _address(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    if not _:
        return text, DEFAULT_PORT
    return host.strip("[]") or "127.0.0.1", int(port)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m protocol.conformance",
        description="Check a cellvision server against SPEC.md.",
    )
    parser.add_argument("address", help="HOST:PORT of the server under test")
    parser.add_argument("--json", action="store_true", help="print results as JSON")
    parser.add_argument("--auth-token", help="token for HELLO, if the server requires one")
    parser.add_argument("--timeout", type=float, default=5.0, help="seconds per answer")
    parser.add_argument("--tls", action="store_true", help="connect with TLS")
    parser.add_argument("--insecure", action="store_true", help="with --tls: skip verification")
    parser.add_argument("-k", dest="select", help="run only checks whose name contains this")
    args = parser.parse_args(argv)
    host, port = _address(args.address)
    target = Target(host, port, args.timeout, args.auth_token, args.tls, not args.insecure)
    try:
        results = run_checks(target, select=args.select)
    except Exception as exc:  # the server cannot even be reached or handshaken
        print(f"conformance: cannot start: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 2
    failed = [r for r in results if r.status in ("fail", "error")]
    if args.json:
        print(
            json.dumps(
                {
                    "target": f"{host}:{port}",
                    "results": [asdict(r) for r in results],
                    "passed": sum(r.status == "pass" for r in results),
                    "failed": len(failed),
                    "skipped": sum(r.status == "skip" for r in results),
                },
                indent=1,
            )
        )
    else:
        width = max(len(r.name) for r in results) if results else 10
        print(f"{'check':<{width}}  section  result  detail")
        for r in results:
            detail = r.detail.splitlines()[0] if r.detail else ""
            print(f"{r.name:<{width}}  {r.section:<7}  {r.status.upper():<6}  {detail}")
        print(
            f"{sum(r.status == 'pass' for r in results)} passed, {len(failed)} failed, "
            f"{sum(r.status == 'skip' for r in results)} skipped against {host}:{port}"
        )
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
