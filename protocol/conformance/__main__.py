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
    """``HOST:PORT``, ``HOST``, ``:PORT``, ``[IPv6]:PORT`` or a bare IPv6 address; ValueError
    when the port is not a number in 1..65535."""
    host, port_text = text, ""
    if text.startswith("["):
        host, bracket, rest = text[1:].partition("]")
        if not bracket or (rest and not rest.startswith(":")):
            raise ValueError(f"bad address {text!r}")
        port_text = rest[1:]
    elif text.count(":") == 1:  # more than one colon: a bare IPv6 address
        host, port_text = text.split(":")
    port = int(port_text) if port_text else DEFAULT_PORT
    if not 0 < port < 65536:
        raise ValueError(f"port {port} out of range")
    return host or "127.0.0.1", port


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
    try:
        host, port = _address(args.address)
    except ValueError as exc:
        parser.error(f"bad server address {args.address!r}: {exc}")
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
