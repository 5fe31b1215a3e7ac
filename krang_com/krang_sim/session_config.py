"""Per-session settings of the simulated robot: a device map on private multicast ports, so that
two sessions (a demo and a test run, say) on one machine never hear each other's CAN frames, and
the node parameters of a sample and control rate other than the configured one (`--rate-hz`)."""

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


def _sim_krang_params():
    return load_config('sim_params.yaml')['sim_krang']['ros__parameters']


def sim_truth_file():
    """The hidden true beta `krang bringup --sim` / `krang demo` simulate (sim_params.yaml)."""
    params = _sim_krang_params()
    return resolve_config_file(params.get('true_beta'), 'sim_true_beta.yaml')


def sim_rate_hz():
    """The configured sample and control rate of the simulated node set (sim_params.yaml)."""
    return float(_sim_krang_params()['feedback_rate_hz'])


def rate_overrides(rate_hz):
    """Per node: the parameters that run the simulated node set at `rate_hz` instead of the
    configured rate (None: {}, the configured rate). They move together: sim_krang takes one
    sample per control step and publishes /clock with each sample (the bridge's device time
    follows the samples); the bridge times the emulated DMU's stream by `imu_sample_period_s`,
    which must be the simulator's sample period; adrc_controller steps once per sample. The
    physics steps at sim_params.yaml's `physics_rate_hz`, so a sample must fall on a physics
    step: a rate that does not divide it raises ValueError (one line)."""
    if rate_hz is None:
        return {}
    physics = float(_sim_krang_params()['physics_rate_hz'])
    rate = float(rate_hz)
    if not rate > 0:
        raise ValueError(f'{rate:g} Hz: a sample rate must be positive')
    steps = physics / rate
    if steps < 1 or abs(steps - round(steps)) > 1e-9 * steps:
        raise ValueError(
            f'{rate:g} Hz: the physics rate ({physics:g} Hz) must be a whole multiple of the '
            'sample rate (e.g. 500, 250 or 100 Hz)'
        )
    return {
        'sim_krang': {'feedback_rate_hz': rate, 'clock_rate_hz': rate},
        'can_bridge': {'imu_sample_period_s': 1.0 / rate},
        'adrc_controller': {'rate_hz': rate},
    }


#: the lowest port a session's buses take (below it: well-known and registered services)
PRIVATE_PORT_MIN = 20000
#: DDS (RTPS) ports: 7400 + 250 * domain + an offset; the offsets below this one in each block
#: of 250 are the discovery and user ports of up to 60 participants per domain
_RTPS_BASE, _RTPS_DOMAIN_GAIN, _RTPS_OFFSETS = 7400, 250, 140


def _ephemeral_port_min():
    """The lowest port the kernel hands out to sockets bound to port 0 (any UDP sender, DDS's
    among them), from /proc; 32768 (Linux's default) where that is not readable."""
    try:
        return int(Path('/proc/sys/net/ipv4/ip_local_port_range').read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def private_port(n=16, rng=None):
    """The first of `n` consecutive UDP ports for a session's udp_multicast buses, drawn at random
    where nothing else on the machine binds: above PRIVATE_PORT_MIN, below the kernel's ephemeral
    range and clear of DDS's ports. python-can's udp_multicast binds with SO_REUSEPORT, which a
    port another program holds without it refuses ("could not create or configure socket"): a
    bus that landed on a DDS participant's port or a sender's ephemeral one did not open."""
    rng = rng or random.Random()
    top = min(_ephemeral_port_min(), 65536) - n
    while True:
        port = rng.randrange(PRIVATE_PORT_MIN, top)
        first, last = ((q - _RTPS_BASE) % _RTPS_DOMAIN_GAIN for q in (port, port + n - 1))
        if first >= _RTPS_OFFSETS and last >= first:
            return port


def session_devices_file(directory, port=None, virtual=False, wheels=None):
    """Write <directory>/can_devices_session.yaml: the package's device map on private UDP ports
    (`port`, `port`+1, ... one per bus: a udp_multicast socket hears every group on its port), or
    with `virtual` on python-can's in-process `virtual` buses (a composed simulation,
    krang_cli.composed). `wheels`: keys of the map's `wheels` section to change (a benchmark's
    TPDO period, say)."""
    port = port or private_port()
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
