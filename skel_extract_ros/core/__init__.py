"""The skeleton extraction method: pure numpy / scipy / Open3D, never rclpy, no messages,
no files.

The steps, by module:
- Step 0, the subject and its rest pose: segmentation, preprocess, rest_pose;
- Step 1, registration (Alg. 1): registration/ (E-step core.gmm, graph terms, M-step),
  deformation_graph, recapture; stream is the per-frame step (subject, rest-pose gate,
  Alg. 1) that both `run` (sequence) and the registration node run;
- Step 2, the skeletal structure: structure (motion clusters, the bone tree), growth (a
  skeleton learned again as key frames come, stable joint ids);
- Step 3, joints (Alg. 2): joints, articulated (LBS, Eq. 8; the bone blocks, Eq. 13-15),
  joint_centres (E_Joint's joint solve, the anchors, the pivot evidence), skeleton_model (the
  learned model);
- live: the learned model fitted to one frame at a time; limb_poses (the live fit's start
  with each limb in a pose learned on the key frames); confidence; bone_rotations;
- pipeline: Steps 0-3 on a sequence, as the nodes learn them from a stream;
- shared: parameters (every parameter's default, range and description), rigid (the
  weighted rigid fit), point_sets, parallel (the one thread pool).

Verbs, one meaning each:
- `obj(frame)` (`__call__`): one frame of a stream in, its result out; the object keeps
  what the stream taught it (SubjectSegmenter, Preprocessor, SubjectFinder,
  FrameRegistrar, StampOrder);
- `register_frame(observed)` / `register(frames)`: Alg. 1 on one frame / on a sequence;
- `fit(data)`: estimate parameters from data and return them (JointEstimation.fit ->
  JointEstimate; a tracker's fit -> one frame's bone transforms); `track(data)`: a fit
  and the joints it puts where;
- `update(window)`: a running model learns from more data (SkeletonGrowth);
- `from_points(points)`: build an object from data (RestPose).
"""
