"""/diagnostics: every node says what state it is in, with its rates and counts, on real DDS."""
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2

from ros_harness import cloud
from skel_extract_ros.nodes.accumulator_node import AccumulatorNode
from skel_extract_ros.nodes.common import STREAM_QOS
from skel_extract_ros.nodes.joint_estimation_node import JointEstimationNode
from skel_extract_ros.nodes.registration_node import RegistrationNode
from skel_extract_ros.sim import NoiseModel, generate_sequence


def latest(statuses, name):
    """The newest DiagnosticStatus of node `name` ('/registration_node'), or None."""
    for array in reversed(list(statuses)):
        for status in array.status:
            if status.name == name:
                return status
    return None


def values(status):
    return {kv.key: kv.value for kv in status.values}


def test_every_node_reports_its_state_rates_and_counts(ros):
    arm = generate_sequence('arm', 6, noise=NoiseModel.none(), seed=2, progress=False)
    statuses = ros.listen('/diagnostics', DiagnosticArray, QoSProfile(depth=100))
    ros.add(RegistrationNode, parameter_overrides=[
        Parameter('rest_pose.n_points', value=600), Parameter('segmentation.enabled', value=False)])
    ros.add(AccumulatorNode, parameter_overrides=[Parameter('window_size', value=100)])
    ros.add(JointEstimationNode)
    names = ('/registration_node', '/accumulator_node', '/joint_estimation_node')
    ros.wait(lambda: all(latest(statuses, n) is not None for n in names), timeout=30.0,
             what='a status from every node')
    before = {n: latest(statuses, n) for n in names}
    # nothing came in yet: each node says what it waits for, as a warning
    assert all(s.level == DiagnosticStatus.WARN for s in before.values())
    assert before['/registration_node'].message.startswith('waiting for input on /points')
    assert before['/accumulator_node'].message == 'waiting for rest_points'
    assert before['/joint_estimation_node'].message == 'waiting for rest_points'
    assert values(before['/registration_node'])['clouds_in'] == '0'

    registered = ros.listen('registered_points', PointCloud2, STREAM_QOS)
    pub = ros.publisher('points', PointCloud2, QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
    ros.wait_matched(pub)
    for i in range(6):
        pub.publish(cloud(arm.clouds[i], arm.stamps_ns[i]))
        ros.wait(lambda: len(registered) == i + 1, what=f'registered frame {i}')

    def registering():
        status = latest(statuses, '/registration_node')
        return status is not None and values(status)['processed'] == '6'
    ros.wait(registering, timeout=30.0, what='the registration status after 6 clouds')
    status = latest(statuses, '/registration_node')
    assert status.level == DiagnosticStatus.OK and status.message.startswith('registering: subject')
    assert status.message.endswith(', frame ok')
    reported = values(status)
    assert reported['skipped'] == '0' and reported['rest_points'] == '600'
    assert float(reported['rate_in_hz']) > 0 and float(reported['latency_ms_median']) > 0

    def collecting():
        status = latest(statuses, '/accumulator_node')
        return status is not None and status.message == 'collecting: 6 of 100 frames'
    ros.wait(collecting, timeout=30.0, what='the accumulator collecting')
    assert float(values(latest(statuses, '/accumulator_node'))['rate_in_hz']) > 0
    ros.wait(lambda: latest(statuses, '/joint_estimation_node').message == 'waiting for skeleton/structure',
             timeout=30.0, what='the joint node waiting for a structure')
