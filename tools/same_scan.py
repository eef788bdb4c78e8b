"""Whether two MCAP scans hold the same data, message by message (gen20, issue 32).

    python tools/same_scan.py A.mcap B.mcap [--ignore-metadata-key version]

Compares, in file order, every message's topic, log and publish time and payload bytes, then the
attachments (name, bytes) and the metadata records (the ``simulation`` record's ``version`` may be
told apart with ``--ignore-metadata-key``). Prints the first differences; exit status 1 if any.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
from itertools import zip_longest

from mcap.reader import make_reader


def _messages(path: str):  # type: ignore[no-untyped-def]
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages(log_time_order=False):
            yield channel.topic, message.log_time, message.publish_time, schema.name if schema else "", message.data


def _extras(path: str, ignore: set[str]) -> tuple[dict[str, str], dict[str, dict[str, str]]]:
    with open(path, "rb") as f:
        reader = make_reader(f)
        atts = {a.name: hashlib.sha256(a.data).hexdigest() for a in reader.iter_attachments()}
    with open(path, "rb") as f:
        records = make_reader(f).iter_metadata()
        meta = {m.name: {k: v for k, v in m.metadata.items() if k not in ignore} for m in records}
    return atts, meta


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("a")
    ap.add_argument("b")
    ap.add_argument("--ignore-metadata-key", action="append", default=[])
    args = ap.parse_args(argv)
    diffs: list[str] = []
    n = 0
    for n, (ma, mb) in enumerate(zip_longest(_messages(args.a), _messages(args.b)), 1):
        if ma is None or mb is None:
            diffs.append(f"message {n}: only in {'b' if ma is None else 'a'}")
            break
        if ma != mb:
            diffs.append(f"message {n}: {ma[0]} t={ma[1]} vs {mb[0]} t={mb[1]}, payload equal: {ma[4] == mb[4]}")
    ea, eb = _extras(args.a, set(args.ignore_metadata_key)), _extras(args.b, set(args.ignore_metadata_key))
    for what, da, db in (("attachments", ea[0], eb[0]), ("metadata", ea[1], eb[1])):
        if da != db:
            diffs.append(f"{what} differ: {sorted(k for k in da.keys() | db.keys() if da.get(k) != db.get(k))}")
    for d in diffs[:20]:
        print(d)
    print(f"{n} messages compared: {'same' if not diffs else f'{len(diffs)} differences'}")
    return 1 if diffs else 0


if __name__ == "__main__":
    sys.exit(main())
