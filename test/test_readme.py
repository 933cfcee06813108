"""The README and docs stay self-contained and match what ships: no reference outside the
repository, a short status whose links land on bench/README.md headings, colcon before the
live camera, the sample bag's command as demo.sh runs it, a node graph, the contract
listing every topic."""
import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / 'README.md').read_text()


def _slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading."""
    text = heading.strip().lower()
    text = re.sub(r'[^\w\- ]', '', text)
    return text.replace(' ', '-')


def test_nothing_points_outside_the_repository():
    tracked = subprocess.run(['git', 'ls-files'], cwd=ROOT, capture_output=True, text=True).stdout.split()
    # bench/ and the tests that read the real-motion data when it is present are left out:
    # they skip what is absent
    checked = [p for p in tracked if not p.startswith(('bench/', 'test/', 'bags/'))
               and p.endswith(('.py', '.md', '.sh', '.xml', '.yaml', '.rviz', '.txt', '.cfg'))]
    assert 'README.md' in checked and 'scripts/demo.sh' in checked
    for path in checked:
        text = (ROOT / path).read_text()
        assert 'DESIGN.md' not in text, path
        assert '../shared' not in text, path


def test_status_is_short_and_its_links_land_on_bench_headings():
    status = README[README.index('**Status**'):README.index('## What the two commands do')].strip()
    assert len(status.splitlines()) <= 10, status
    headings = {_slug(line.lstrip('#')) for line in (ROOT / 'bench' / 'README.md').read_text().splitlines()
                if line.startswith('#')}
    links = re.findall(r'\(bench/README\.md#([^)]+)\)', status)
    assert len(links) >= 3
    for anchor in links:
        assert anchor in headings, anchor


def test_colcon_comes_before_the_live_camera_and_the_examples_match_the_sample_bag():
    assert README.index('## Building with colcon') < README.index('## Running against a live camera')
    # the bag's topics are depth images: the replay example says so
    from skel_extract_ros.codecs.bag import cloud_topics
    topics = cloud_topics(ROOT / 'bags' / 'sample_wave')
    assert list(topics) == ['/camera/depth/image_raw']
    assert 'ros2 bag play bags/sample_wave --clock' in README
    assert '/camera/depth/points:=/points' not in README
    # demo.sh rebuilds the shipped bag with the arguments the README quotes
    demo = (ROOT / 'scripts' / 'demo.sh').read_text()
    args = re.search(r'SAMPLE_BAG_ARGS=\(([^)]*)\)', demo).group(1)
    flat = ' '.join(README.split())
    assert f'--bvh dataset-2_wave-both-hands_active_001.bvh {args} --out bags/sample_wave' in flat


def test_node_graph_and_contract_cover_every_topic():
    from skel_extract_ros.app.replay import OUTPUT_TOPICS
    graph = README[README.index('```mermaid'):]
    graph = graph[:graph.index('```', 3)]
    for node in ('registration_node', 'accumulator_node', 'joint_estimation_node'):
        assert node in graph
    contract = (ROOT / 'docs' / 'contract.md').read_text()
    for topic, _type, _latched in OUTPUT_TOPICS:
        name = topic.lstrip('/')
        if name != 'diagnostics':
            assert f'`{name}`' in contract, name
            assert name in graph or name in ('rest_points',), name
    assert 'docs/contract.md' in README
