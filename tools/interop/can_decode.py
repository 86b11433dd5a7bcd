#!/usr/bin/env python3
"""CAN interop counterpart for tests/cli_run.rs, built on software hapcloud did not write:
cantools loads hapcloud.dbc (strict) and reads a candump -L log with its own log reader (the
format can-utils' `candump -L` and `hapcloud run --can-log` write).

Usage: can_decode.py DBC LOG
Prints one JSON line per logged frame, in log order: {"id": ID, "name": NAME or null,
"signals": {SIGNAL: VALUE}} with every signal scaled and without value tables; a line the
reader cannot parse exits non-zero naming it.
"""

import json
import sys

import cantools


def main():
    db = cantools.database.load_file(sys.argv[1], strict=True)
    with open(sys.argv[2]) as log:
        for n, (line, frame) in enumerate(cantools.logreader.Parser(log).iterlines(True), 1):
            if frame is None:
                sys.exit(f"{sys.argv[2]}:{n}: cantools cannot read {line!r}")
            try:
                msg = db.get_message_by_frame_id(frame.frame_id)
            except KeyError:
                msg = None
            signals = msg.decode(frame.data, decode_choices=False) if msg else {}
            print(json.dumps({
                "id": frame.frame_id,
                "name": msg.name if msg else None,
                "signals": {k: float(v) for k, v in signals.items()},
            }))


if __name__ == "__main__":
    main()
