"""The nodes' parameters: which dataclasses each node declares (the method's, from core,
and the node's own, here), under which ROS name prefix.

A node's parameters are the fields of its sections' dataclasses, declared in this order;
the YAML file, the README tables and `skel-extract run --params` follow the same map.
"""
from __future__ import annotations

from dataclasses import dataclass

from ..core.growth import GrowthSchedule
from ..core.joints import JointParams
from ..core.parameters import parameter, validate
from ..core.preprocess import PreprocessParams
from ..core.registration import RegistrationParams
from ..core.rest_pose import RestPoseParams
from ..core.segmentation import SegmentationParams
from ..core.structure import StructureParams


@dataclass
class RegistrationNodeParams:
    """The registration node's own parameters (input, queues, priority); all read-only."""

    queue_size: int = parameter(1, 'subject clouds waiting for the registration at most once the first window is '
                                'learned; older ones are skipped (and counted) when registration falls behind the '
                                'camera (filtered_points still comes for every cloud)', 1, 100_000)
    learning_queue_size: int = parameter(60, 'subject clouds waiting for the registration at most while the first '
                                         'window is learned (from the rest pose to the first skeleton/structure), '
                                         'registered in order, so the window is consecutive camera frames as '
                                         "skel-extract run's; when full, new clouds are skipped (counted), before "
                                         'their segmentation until the first skeleton is described. Set it to at '
                                         "least the accumulator's window_size", 1, 100_000)
    lossless: bool = parameter(False, 'never skip a cloud: when registration falls behind, segmentation waits for '
                               'it and so does the input (bag replay with input_reliability reliable; replay '
                               'sets it)')
    input_reliability: str = parameter('best_effort', 'QoS of the points subscription: best_effort (sensor data, '
                                       'matches every driver) or reliable (lossless bag replay; needs a reliable '
                                       'publisher)', choices=('best_effort', 'reliable'))
    input: str = parameter('cloud', 'what the camera driver publishes: cloud (PointCloud2 on points) or '
                           'depth_image (Image on depth/image, 16UC1 mm or 32FC1 m, with CameraInfo on '
                           'depth/camera_info)', choices=('cloud', 'depth_image'))
    registration_niceness: int = parameter(10, 'added to the nice value of the child process that runs Alg. 1 '
                                           'once the first window is learned (skeleton/structure): when the cores '
                                           "are short, the joint node's Alg. 2 and then the live path "
                                           '(segmentation, filtered_points, the joint fit) go first and growing '
                                           'the skeleton waits; while learning the first window it runs at the '
                                           "node's priority; 0 = never lowered (nor with lossless)", 0, 19)
    registration_sched_idle: bool = parameter(True, 'when the priority of the child running Alg. 1 is lowered '
                                              "(registration_niceness), it also enters Linux's idle scheduling "
                                              'class (SCHED_IDLE): it gets a core only when no other task wants '
                                              'it, so the live path never waits for the scheduler to preempt it '
                                              'and growing the skeleton uses the idle CPU; false = the nice value '
                                              'only')
    live_start: bool = parameter(True, "once a skeleton is tracked, register each frame starting from the joint "
                                 "node's newest posed model (skeleton/posed_points: the live fit of a frame since "
                                 'the last registered one) instead of from that last registered frame, up to '
                                 'seconds old; false = always from the last registered frame (Alg. 1 as in '
                                 'skel-extract run). Not with lossless')

    def __post_init__(self):
        validate(self)


@dataclass
class AccumulatorNodeParams:
    """The accumulator node's own parameters."""

    lossless: bool = parameter(False, 'learn every window that comes due, in order, as skel-extract run learns '
                               'them (bag replay; replay sets it): windows that come due during an extraction wait '
                               'in a queue; false = a live camera: a newer window replaces a waiting one')

    def __post_init__(self):
        validate(self)


@dataclass
class JointNodeParams:
    """The joint estimation node's own parameters (the live fit, the buffer, the markers)."""

    buffer_size: int = parameter(300, 'registered + filtered frames kept to find a structure window in', 2, 100_000,
                                 live=True)
    live_frames: str = parameter('camera', 'which frames get live joints: camera (every filtered_points frame, the '
                                 'learned skeleton fitted to its subject points, started from the newest registered '
                                 'frame; never waits for registration) or registered (registered frames only, as '
                                 'skel-extract run; lossless replay)', choices=('camera', 'registered'))
    live_iterations: int = parameter(3, 'EM iterations of the live fit to a camera frame (each: the whole-body '
                                     "move, then the bone-by-bone update with the joint weight growing to Alg. 2's "
                                     'at the last)', 1, 100, live=True)
    live_sweeps: int = parameter(2, "the fit of each registered frame (live_frames registered, and the camera "
                                 "frames' start): bone-by-bone passes after the rigid initialisation", 0, 100,
                                 live=True)
    live_chain: bool = parameter(True, 'with live_frames camera: each camera frame is also fitted from the pose '
                                 'served for the frame before, when that second fit still ends before the next '
                                 'frame comes, and the fit whose joints its points support better (the higher mean '
                                 'confidence) is served (fast limbs); each of the two fits on half the points one '
                                 'fit uses. false: one fit, from the newest registered pose', live=True)
    live_limb_poses: bool = parameter(True, 'with live_frames camera: the fit from the registered pose starts '
                                      "each limb the frame's points show elsewhere in the one of its poses on the "
                                      'frames the skeleton was learned on that explains them clearly better (a '
                                      "hand that swung beyond the fit's reach). false: the registered pose as it "
                                      'is', live=True)
    provisional_skeleton: bool = parameter(True, "with live_frames camera: track Step 2's skeleton (each point on "
                                           'its bone) as soon as a structure arrives, described with provisional '
                                           "true, while Alg. 2 runs; Alg. 2's model then replaces it under the same "
                                           'joint names. false: the first joints wait for Alg. 2 (seconds)',
                                           live=True)
    estimation_niceness: int = parameter(5, 'added to the nice value of the thread running Alg. 2 (and of its '
                                         'pool): the live fit of every camera frame, in the same process, comes '
                                         'first, and Alg. 2 before the registration (registration_niceness, '
                                         'larger); 0 = same priority', 0, 19)
    joint_diameter: float = parameter(0.04, 'diameter of the joint spheres in skeleton/markers, m', 1e-4, 10.0,
                                      live=True)
    lossless: bool = parameter(False, 'run Alg. 2 on every skeleton/structure, in order (bag replay; replay sets '
                               'it): structures that come while it runs wait in a queue; false = a live camera: a '
                               'newer structure replaces a waiting one')

    def __post_init__(self):
        validate(self)


@dataclass(frozen=True)
class Section:
    """One dataclass of a node's parameters: `key` names its instance (SkeletonPipeline's
    keyword for the method's; 'node' for the node's own), `prefix` its ROS names."""

    key: str
    cls: type
    prefix: str = ''
    title: str = ''


NODE_KEY = 'node'
NODES = {
    'registration_node': (Section('registration', RegistrationParams, title='Alg. 1, Eq. (1)-(7)'),
                          Section('rest_pose', RestPoseParams, 'rest_pose.', 'the rest pose (Sec. 4)'),
                          Section('preprocess', PreprocessParams, 'preprocess.', 'per-frame cleaning'),
                          Section('segmentation', SegmentationParams, 'segmentation.',
                                  'the subject in a room: the connected region that moves'),
                          Section(NODE_KEY, RegistrationNodeParams, title='the node: input, queues, priority')),
    'accumulator_node': (Section('structure', StructureParams, title='Sec. 5: skeletal structure'),
                         Section('schedule', GrowthSchedule, title='when the skeleton is learned'),
                         Section(NODE_KEY, AccumulatorNodeParams, title='the node: lossless replay')),
    'joint_estimation_node': (Section('joints', JointParams, title='Sec. 6, Alg. 2, Eq. (11)-(15), Table 1'),
                              Section(NODE_KEY, JointNodeParams, title='the node: live fit, buffer, markers')),
}

# When a running node applies its live parameters (field metadata `live`), for every node
# that has any (the README says it).
LIVE_FROM = {'accumulator_node': 'the next registered frame',
             'joint_estimation_node': 'the next frame (joint_diameter, live_iterations, live_sweeps, buffer_size) '
                                      "or the next skeleton/structure (the method's parameters, "
                                      'provisional_skeleton, live_chain, live_limb_poses)'}
