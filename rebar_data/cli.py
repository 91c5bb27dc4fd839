"""`rebar`: the command line. User errors are one line on stderr and exit status 2, never a traceback.

Each command group lives beside the code it drives, in a ``commands`` module with a ``register``
function; this module only assembles them.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from rebar_data.config import ConfigError
from rebar_data.dataset.layout import DatasetFormatError
from rebar_data.ray_cluster import BackendError

COMMAND_MODULES = [
    "rebar_data.geometry.commands",
    "rebar_data.render.commands",
    "rebar_data.dataset.commands",
    "rebar_data.bench",
    "rebar_data.servo.commands",
    "rebar_data.perception.commands",
]
# modules whose commands join another module's group: `rebar dataset publish|diff`
SUBCOMMAND_MODULES = {"rebar_data.publish.commands": "rebar_data.dataset.commands"}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="rebar", description="Synthetic rebar data, detector and servo evaluation."
    )
    sub = p.add_subparsers(dest="command", required=True)
    groups = {name: importlib.import_module(name).register(sub) for name in COMMAND_MODULES}
    for name, group in SUBCOMMAND_MODULES.items():
        importlib.import_module(name).add_commands(groups[group])
    return p


def main(argv: list[str] | None = None) -> int:
    from rebar_data.perception.commands import forward_dataset_detect

    args = build_parser().parse_args(forward_dataset_detect(list(sys.argv[1:] if argv is None else argv)))
    try:
        result = args.func(args)
    except (ConfigError, DatasetFormatError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        from rebar_data.outputs import NO_SPACE

        if e.errno not in NO_SPACE:
            raise
        # a full disk where no command said what it needs: the file it could not write
        where = f"{e.filename}: " if e.filename else ""
        print(
            f"error: {where}no space left on the device; accepted: free space there and run again",
            file=sys.stderr,
        )
        return 2
    except KeyboardInterrupt as e:
        # a long command's own (BuildInterrupted, MapInterrupted) says what it kept and how to go on
        print(str(e) or "interrupted", file=sys.stderr)
        return 130
    except BackendError as e:  # a task failed on the Ray cluster after its retries; what finished is kept
        print(f"error: {e}", file=sys.stderr)
        return 1
    return int(result or 0)


if __name__ == "__main__":
    sys.exit(main())
