#!/usr/bin/env python3
"""Screenshots of every console page, from the real server, for docs/console.md.

    python scripts/console_screenshots.py                 # into docs/console/
    python scripts/console_screenshots.py --out /tmp/shots

Starts the real server with the example cell (tests/helpers/console_server.py: ports 0, the
console on, a token) and walks docs/console.md's tuning of ``magnet_check`` in headless
Chromium (tests/helpers/console_walkthrough.py, the steps the walkthrough test checks), saving
a 1024-pixel-wide PNG of each page as it goes: login, cameras, inspections, results, server,
and any page added since. Needs Chromium and chromedriver (scripts/browser_setup.sh) and
selenium (the test extra). Exit status 0 when every step held.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT), str(ROOT / "tests" / "helpers")]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "console")
    args = parser.parse_args(argv)

    from browser import headless_chromium
    from console_server import console_server
    from console_walkthrough import walk

    with (
        tempfile.TemporaryDirectory(prefix="cellvision-shots-") as folder,
        console_server(Path(folder)) as server,
        headless_chromium() as driver,
    ):
        walk(driver, server, args.out)
    for shot in sorted(args.out.glob("*.png")):
        print(shot)
    return 0


if __name__ == "__main__":
    sys.exit(main())
