"""``python -m protocol.conformance HOST:PORT [--json] [--profile NAME]``."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from dataclasses import asdict

from ..constants import DEFAULT_PORT
from . import CHECKS, PROFILES, Profile, Target, run_checks

_EPILOG = """\
profiles (what the server under test need not offer):
{profiles}
A check that needs what the profile leaves out is not run and is reported N/A, "not applicable
(profile ...)", never PASS. Under "full" a check is SKIPped, with the reason, when the server
offers nothing to run it on (e.g. no server-side camera). The check "reload" sends RELOAD, which
makes a server re-read its configuration file: against a cell in production, leave it out
(--profile minimal, or -k to choose checks).

exit status: 0 when no check failed, 1 when one failed, 2 when the server could not be reached
or did not complete the handshake.
"""


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
        description="Check a cellvision server against SPEC.md, section by section.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=_EPILOG.format(profiles="\n".join(map(_describe, PROFILES.values()))),
    )
    parser.add_argument("address", help="HOST:PORT of the server under test")
    parser.add_argument("--json", action="store_true", help="print results as JSON")
    parser.add_argument("--auth-token", help="token for HELLO, if the server requires one")
    parser.add_argument("--timeout", type=float, default=5.0, help="seconds per answer")
    parser.add_argument("--tls", action="store_true", help="connect with TLS")
    parser.add_argument("--insecure", action="store_true", help="with --tls: skip verification")
    parser.add_argument("-k", dest="select", help="run only checks whose name contains this")
    parser.add_argument(
        "--profile",
        choices=sorted(PROFILES),
        default="full",
        help="what the server need not offer (default: full, everything; below)",
    )
    args = parser.parse_args(argv)
    try:
        host, port = _address(args.address)
    except ValueError as exc:
        parser.error(f"bad server address {args.address!r}: {exc}")
    target = Target(host, port, args.timeout, args.auth_token, args.tls, not args.insecure)
    try:
        results = run_checks(target, select=args.select, profile=PROFILES[args.profile])
    except Exception as exc:  # the server cannot even be reached or handshaken
        print(f"conformance: cannot start: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 2
    failed = [r for r in results if r.status in ("fail", "error")]
    if args.json:
        print(
            json.dumps(
                {
                    "target": f"{host}:{port}",
                    "profile": args.profile,
                    "results": [asdict(r) for r in results],
                    "passed": sum(r.status == "pass" for r in results),
                    "failed": len(failed),
                    "skipped": sum(r.status == "skip" for r in results),
                    "not_applicable": sum(r.status == "n/a" for r in results),
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
        not_applicable = sum(r.status == "n/a" for r in results)
        print(
            f"{sum(r.status == 'pass' for r in results)} passed, {len(failed)} failed, "
            f"{sum(r.status == 'skip' for r in results)} skipped"
            + (f", {not_applicable} not applicable" if not_applicable else "")
            + f" against {host}:{port}"
            + (f" (profile {args.profile})" if args.profile != "full" else "")
        )
    return 1 if failed else 0


def _describe(profile: Profile) -> str:
    text = f"  {profile.name:<8} {profile.description}"
    left_out = [c.name for c in CHECKS if c.needs & profile.omits]
    if left_out:
        text += f"\n  {'':<8} (checks left out: {', '.join(left_out)})"
    return text


if __name__ == "__main__":
    sys.exit(main())
