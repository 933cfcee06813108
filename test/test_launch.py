"""launch/skel_extract.launch.py and rviz/skel_extract.rviz: loaded with the launch package
where it is installed (a ROS install), else read as source: the arguments it declares, the
remaps of both inputs, and an RViz config that shows topics the nodes publish."""
import ast
import importlib.util
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
LAUNCH_FILE = ROOT / 'launch' / 'skel_extract.launch.py'
RVIZ_FILE = ROOT / 'rviz' / 'skel_extract.rviz'
EXPECTED = {'input': ('cloud', ['cloud', 'depth_image']), 'points': ('/camera/depth/points', None),
            'depth_image': ('/camera/depth/image_raw', None), 'camera_info': ('/camera/depth/camera_info', None),
            'params_file': ('', None), 'namespace': ('', None), 'rviz': ('false', ['true', 'false']),
            'use_sim_time': ('false', ['true', 'false'])}


def _declared_in_source() -> dict:
    """{name: (default, choices)} of the ARGUMENTS literal of the launch file."""
    tree = ast.parse(LAUNCH_FILE.read_text())
    [node] = [n for n in tree.body if isinstance(n, ast.Assign) and n.targets[0].id == 'ARGUMENTS']
    return {name: (default, list(choices) if choices else None)
            for name, default, _text, choices in ast.literal_eval(node.value)}


def test_launch_arguments_and_remaps_in_the_source():
    assert _declared_in_source() == EXPECTED
    source = LAUNCH_FILE.read_text()
    for remap in ("('points', LaunchConfiguration('points'))",
                  "('depth/image', LaunchConfiguration('depth_image'))",
                  "('depth/camera_info', LaunchConfiguration('camera_info'))"):
        assert remap in source, remap
    assert "{'input': LaunchConfiguration('input')}" in source
    assert "IfCondition(LaunchConfiguration('rviz'))" in source and 'PushRosNamespace' in source
    # installed where the launch file looks for them
    setup = (ROOT / 'setup.py').read_text()
    assert "glob('rviz/*.rviz')" in setup and "glob('launch/*.launch.py')" in setup


def test_launch_description_loads_where_launch_is_installed(monkeypatch):
    launch_ros = pytest.importorskip('launch_ros', reason='the launch package is not installed (no ROS install)')
    import ament_index_python.packages
    from launch.actions import DeclareLaunchArgument
    # the source tree has the share directory's layout (params/, rviz/)
    monkeypatch.setattr(ament_index_python.packages, 'get_package_share_directory', lambda _name: str(ROOT))
    spec = importlib.util.spec_from_file_location('skel_extract_launch', LAUNCH_FILE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    description = module.generate_launch_description()
    declared = {a.name: (a.default_value[0].text if a.default_value else None, a.choices)
                for a in description.entities if isinstance(a, DeclareLaunchArgument)}
    assert declared == EXPECTED
    assert launch_ros is not None


def test_rviz_config_shows_the_subject_cloud_markers_and_joints():
    config = yaml.safe_load(RVIZ_FILE.read_text())
    displays = {d['Class']: d for d in config['Visualization Manager']['Displays']}
    topics = {cls: d['Topic']['Value'] for cls, d in displays.items() if 'Topic' in d}
    assert topics == {'rviz_default_plugins/PointCloud2': 'filtered_points',
                      'rviz_default_plugins/MarkerArray': 'skeleton/markers',
                      'rviz_default_plugins/PoseArray': 'skeleton/joints'}
    # relative names (the launch file's namespace applies), published by the nodes
    from skel_extract_ros.app.replay import OUTPUT_TOPICS
    published = {topic for topic, _type, _latched in OUTPUT_TOPICS}
    assert set(topics.values()) <= published
    assert set(displays['rviz_default_plugins/MarkerArray']['Namespaces']) == {'joints', 'names', 'bones'}
    assert config['Visualization Manager']['Global Options']['Fixed Frame'] == 'camera_depth_optical_frame'


def test_package_xml_declares_every_ros_package_the_code_imports():
    import re
    import xml.etree.ElementTree as ElementTree
    manifest = ElementTree.parse(ROOT / 'package.xml').getroot()
    declared = {e.text for e in manifest.iter('exec_depend')}
    imported = set()
    for path in list((ROOT / 'skel_extract_ros').rglob('*.py')) + [LAUNCH_FILE]:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                imported.update(alias.name.split('.')[0] for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                imported.add(node.module.split('.')[0])
    ros = {name for name in imported if re.search(r'_(msgs|srvs|interfaces)$', name)
           or name in ('rclpy', 'launch', 'launch_ros', 'ament_index_python')}
    assert {'trajectory_msgs', 'launch', 'launch_ros', 'rcl_interfaces', 'ament_index_python'} <= ros
    assert ros <= declared, f'imported, not declared: {sorted(ros - declared)}'
    # no lint test is declared that does not run
    assert not {e.text for e in manifest.iter('test_depend')} & {'ament_copyright', 'ament_flake8', 'ament_pep257'}
    assert manifest.find('license').text == 'Apache-2.0'
    assert 'Apache License' in (ROOT / 'LICENSE').read_text()[:200]
    notice = (ROOT / 'bags' / 'NOTICE.md').read_text()
    assert 'CC BY-NC 4.0' in notice and 'Bandai Namco Research' in notice
