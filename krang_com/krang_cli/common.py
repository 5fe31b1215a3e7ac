"""Small helpers shared by the subcommands."""

import json


def print_json(payload):
    """Machine-readable result: always the last line of stdout."""
    print(json.dumps(payload, sort_keys=False))
