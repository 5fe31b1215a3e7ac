"""Per-session files for the simulated robot: a device map on private multicast ports, so that two
sessions (a demo and a test run, say) on one machine never hear each other's CAN frames."""

import random
from pathlib import Path

import yaml

from krang_can_bridge.config import default_devices_file, load_devices
from krang_model.config import config_path, load_config
from krang_model.files import write_text


def resolve_config_file(name, default):
    """A file parameter: empty -> config/<default>; a bare name -> config/<name>; else the path
    itself."""
    name = str(name or default)
    path = Path(name)
    return path if path.is_absolute() or path.exists() else config_path(name)


def sim_truth_file():
    """The hidden true beta `krang bringup --sim` / `krang demo` simulate (sim_params.yaml)."""
    params = load_config('sim_params.yaml')['sim_krang']['ros__parameters']
    return resolve_config_file(params.get('true_beta'), 'sim_true_beta.yaml')


def session_devices_file(directory, port=None, virtual=False, wheels=None):
    """Write <directory>/can_devices_session.yaml: the package's device map on private UDP ports
    (`port`, `port`+1, ... one per bus: a udp_multicast socket hears every group on its port), or
    with `virtual` on python-can's in-process `virtual` buses (a composed simulation,
    krang_cli.composed). `wheels`: keys of the map's `wheels` section to change (a benchmark's
    TPDO period, say)."""
    port = port or random.Random().randrange(20000, 60000, 16)
    base = default_devices_file()
    config = load_devices(base)

    def bus_entry(k, name, bus):
        if virtual:
            return {'interface': 'virtual', 'channel': f'krang-{name}'}
        return {
            'interface': bus.interface,
            'channel': bus.channel,
            'options': {**dict(bus.options), 'port': port + k},
        }

    doc = {
        'extends': str(Path(base).resolve()),
        'dbc_file': str(Path(config.dbc_path).resolve()),
        'buses': {
            name: bus_entry(k, name, bus)
            for k, (name, bus) in enumerate(sorted(config.buses.items()))
        },
    }
    if wheels:
        with open(base) as f:
            doc['wheels'] = {**yaml.safe_load(f)['wheels'], **wheels}
    path = Path(directory) / 'can_devices_session.yaml'
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text(
        path, '# generated for one simulated session\n' + yaml.safe_dump(doc, sort_keys=False)
    )
    return path
