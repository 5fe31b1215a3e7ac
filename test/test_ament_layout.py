"""`colcon build` puts every executable where `ros2 run krang_com <exe>` looks (DESIGN.md §2)."""
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO

EXECUTABLES = ('krang', 'can_bridge', 'adrc_controller', 'pose_server', 'com_estimator', 'mcap_recorder', 'sim_krang')


def test_package_xml_is_format_3_ament_python():
    import xml.etree.ElementTree as ET
    root = ET.parse(REPO / 'package.xml').getroot()
    assert root.get('format') == '3'
    assert root.findtext('name') == 'krang_com'
    assert root.find('export/build_type').text == 'ament_python'
    assert (REPO / 'resource' / 'krang_com').exists()


@pytest.mark.skipif(shutil.which('colcon', path=str(Path(sys.executable).parent)) is None, reason='colcon not installed')
def test_colcon_install_layout(tmp_path):
    colcon = str(Path(sys.executable).parent / 'colcon')
    result = subprocess.run(
        [colcon, 'build', '--base-paths', str(REPO), '--build-base', str(tmp_path / 'build'),
         '--install-base', str(tmp_path / 'install'), '--event-handlers', 'console_direct-'],
        cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    prefix = tmp_path / 'install' / 'krang_com'
    for exe in EXECUTABLES:
        assert (prefix / 'lib' / 'krang_com' / exe).is_file(), exe
    assert (prefix / 'share' / 'ament_index' / 'resource_index' / 'packages' / 'krang_com').exists()
    assert (prefix / 'share' / 'krang_com' / 'package.xml').exists()
    assert (prefix / 'share' / 'krang_com' / 'config' / 'robot.yaml').exists()
