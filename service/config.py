"""Typed configuration with documented defaults, loaded from `configs/*.yaml`.

Every threshold of the pipeline lives here. Names follow RTAB-Map's parameters where one
exists (its name is given in the field comment). A YAML file only needs the keys it changes:

    odometry:
      features: 1000
    keyframe:
      linear_update: 0.1
"""
from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path

import yaml


@dataclass
class FeatureConfig:
    max_features: int = 1000  # ORB keypoints per 640×480 image, more in proportion on larger images (Vis/MaxFeatures)
    grid_rows: int = 4  # keypoints are spread over a grid of cells ...
    grid_cols: int = 6  # ... each cell keeps its best max_features/(rows*cols)
    fast_threshold: int = 12  # FAST threshold; cells retry at min_fast_threshold if empty
    min_fast_threshold: int = 5
    scale_factor: float = 1.2  # ORB pyramid
    levels: int = 8
    min_depth: float = 0.2  # metres; nearer / farther depth readings are ignored
    max_depth: float = 6.0  # (Vis/MaxDepth is 0 = inf in RTAB-Map; Kinect noise grows as z^2)
    depth_noise: float = 0.003  # RGB-D depth std. dev. = this × z² (m; Kinect noise plus colour/depth misregistration), weighs depth in pose refinement
    distortion: list[float] | None = None  # lens distortion k1, k2, p1, p2[, k3] of the camera's raw images, overriding the source's (TUM fr1/fr2's published values, ROS CameraInfo D, a camera's info); [] ignores it; null keeps the source's. Feature coordinates are undistorted, depth read at the raw pixel


@dataclass
class StereoConfig:
    max_row_diff: float = 2.0  # px, rectified rows of a left/right match may differ this much
    min_disparity: float = 1.0  # px
    max_disparity: float = 0.4  # fraction of image width
    max_hamming: int = 60  # descriptor distance for a stereo match
    max_depth: float = 40.0  # metres; farther stereo depth is biased (1/disparity is convex) and skews scale
    disparity_sigma: float = 1.0  # px, disparity std. dev.: depth std. dev. = z² σ / (f·baseline), weighs far points in pose refinement
    disparity_offset: float = 0.0  # px added to every measured disparity (a rectification yaw error shifts them all alike); the start of the online estimate
    self_calibrate: bool = True  # estimate that offset online, as a 7th parameter of each frame's refined pose
    calib_window: int = 10  # tracked frames whose estimates are averaged (weighted by their information)
    calib_min_frames: int = 3  # fewer frames in the window: keep the last estimate
    calib_max_sigma: float = 0.2  # px; the window's estimate is used when its std. dev. is below this
    calib_max_offset: float = 5.0  # px, the estimate is limited to ± this


@dataclass
class OdometryConfig:
    match_ratio: float = 0.8  # nearest-neighbour distance ratio (Kp/NndrRatio, Vis/CorNNDR)
    max_hamming: int = 80  # reject matches farther than this (of 256 bits)
    guided_radius: float = 20.0  # px, matches must reproject this close to the predicted pose
    min_inliers: int = 20  # PnP inliers to accept a pose (Vis/MinInliers)
    confident_inliers: int = 60  # fewer: also try unguided matching, then (RGB-D) depth ICP
    confident_sigma_rotation: float = 0.3  # deg; (RGB-D) a PnP pose whose rotation σ (from its refinement's Hessian) is larger ...
    confident_sigma_translation: float = 0.01  # m; ... or whose translation σ is larger is not confident either: depth ICP is tried
    pnp_reprojection_error: float = 2.0  # px (Vis/PnPReprojError)
    pnp_iterations: int = 200  # RANSAC iterations (Vis/PnPIterations is 100; we refine after)
    pnp_confidence: float = 0.999
    pnp_ransac_max_sigma: float = 0.0  # px; > 0: RANSAC samples and scores only the matches whose keypoint σ (scale_factor^octave) is at most this (1.45: the three finest levels), when at least 40 are; the inliers are then selected among all under the refined pose. 0: all
    max_translation: float = 0.0  # m between frames, 0 = unlimited (Odom/MaxTranslation)
    local_map_size: int = 3000  # 3-D points kept in the local map (OdomF2M/MaxSize)
    motion_model: bool = True  # predict with constant velocity (Odom/GuessMotion)
    max_jump_factor: float = 3.0  # a pose may differ from the prediction by this × the last motion ...
    max_jump_min_m: float = 0.15  # ... or at least this many metres ...
    max_jump_min_rad: float = 0.15  # ... and radians
    max_depth_residual: float = 0.05  # reject a pose when the inliers' predicted depth differs from the measured by more (median, relative)
    # The local map takes a tracked frame's features when the camera moved or turned this
    # much since the last map update, or when inliers fell below map_update_ratio × the
    # inliers of that update (OdomF2M: Odom/KeyFrameThr 0.3). Independent of graph keyframes.
    map_update_linear: float = 0.02
    map_update_angular: float = 0.02
    map_update_ratio: float = 0.6
    icp_fallback: bool = True  # RGB-D: register depth (point-to-plane ICP) when features fail
    icp_min_inlier_ratio: float = 0.3  # associated depth points needed to trust ICP
    icp_min_conditioning: float = 0.002  # smallest/largest Hessian eigenvalue: below = degenerate
    # RGB-D whose depth image is stamped apart from the colour image (the TUM player gives the
    # depth stamp; fr1/desk: ±15 ms, every other frame the other way): each keypoint's depth
    # point is moved by the motion model's motion over that time into the colour image's camera
    depth_time_compensation: bool = True  # RGB-D: move each keypoint's depth point by the motion between the depth and colour stamps
    # ... and its σ grows by this × how far that motion moved the point (translation + depth ×
    # rotation): the constant-velocity motion is a guess (fr1/desk with loops 2.65 -> 2.52 cm)
    depth_time_sigma: float = 0.5  # × the depth-time motion's displacement of a point, added to its depth σ
    # RGB-D: at each map update the inliers' depth readings refine their map points (an
    # information-weighted mean of the readings at the tracked poses, a structure-only local
    # BA), where a point otherwise keeps its first reading. Off: on fr1/desk odometry alone
    # 3.21 / 3.21 / 4.16 -> 3.09 / 3.09 / 2.96 cm on three RANSAC draws but not on three others,
    # and with loops 2.52-2.55 -> 2.62-2.63 (issue 26, docs/benchmarks.md)
    map_point_fusion: bool = False  # RGB-D: refine local-map points with the depth readings of later map updates
    fusion_gate: float = 3.0  # a reading farther than this (Mahalanobis, point's and reading's covariance) is left out
    fusion_readings: int = 10  # readings fused into a point after its first, at most
    # RGB-D: every window_ba_every map updates, the poses of the last window_ba_size map updates
    # and the points they observe are refined jointly (reprojection and measured depth, Huber;
    # window_ba_fixed older map updates held), the points written back into the local map, a
    # point seen once moved with its map update's pose, and tracking continues from the refined
    # pose (ORB-SLAM's local mapping feeding tracking; service/tracking/window_ba.py). Off: with
    # these defaults fr1/desk odometry 3.21 / 3.21 / 4.16 -> 2.77 / 2.58 / 2.64 cm (three RANSAC
    # draws) and with loops 2.55 -> 2.47, 7-Scenes 3.68 / 3.22 -> 3.53 / 3.07, cabinet 2.59 / 2.11
    # -> 2.70 / 2.15, but tracking frames/s 0.74x; with window_ba_points 400 0.9x but 7-Scenes
    # odometry 4.90 (issue 26, docs/benchmarks.md)
    window_ba: bool = False  # RGB-D: windowed BA of the local map's map updates (poses and points) fed back to tracking
    window_ba_size: int = 5  # map updates whose poses are adjusted
    window_ba_fixed: int = 10  # older map updates held fixed (their observations still constrain the points)
    window_ba_history: int = 0  # > 0: the held ones are those of the last this many map updates before the window that see its points most (ORB-SLAM's); 0: the ones just before the window
    window_ba_every: int = 3  # map updates between two adjustments
    window_ba_iterations: int = 5  # Levenberg–Marquardt iterations per adjustment
    window_ba_points: int = 0  # > 0: at most this many points per adjustment, those seen most often; 0: all
    # window_ba_hold: returned with window_ba and the fourth pass's reuse settings (map_reuse,
    # match_from_map, match_tile 160, min_observations 3, at map updates): fr1/desk odometry mean
    # of six draws 2.20 cm, with loops 2.24 (today 2.55), 7-Scenes 3.31 / 3.05, cabinet
    # 2.40 / 2.25, but tracking 0.56-0.70x (issue 26, docs/benchmarks.md, eighth pass); with
    # window_ba_every 5 and pnp_ransac_max_sigma 1.45 tracking 0.72x alone, ~0.9x end to end (ninth pass),
    # fr1/desk 2.14 / 2.32, cabinet 2.44 / 2.37, KITTI a / b 7.66 / 6.96 cm (today 7.03 / 22.19)
    window_ba_hold: str = "none"  # points the adjustment holds: none; old (made before its oldest map update); returned (brought back by map_reuse)
    # Map reuse on revisits (ORB-SLAM tracks against the points of the keyframes covisible with
    # the current one, old ones included): points trimmed from the local map go to an archive
    # (at most map_reuse_archive points, the least recently seen dropped beyond) instead of
    # being dropped, and archived points inside the predicted view (in front, inside the image,
    # at a distance within map_reuse_distance_ratio of and seen within map_reuse_angle of their
    # first sighting: ORB-SLAM's isInFrustum) come back into the local map, so a revisit tracks
    # against the old points again (issue 26, docs/benchmarks.md "Map reuse on revisits"). Off:
    # with match_from_map, match_tile 160, map_reuse_min_observations 3 and at map updates,
    # fr1/desk odometry 3.34 -> 2.62 cm (mean of six RANSAC draws, lower on each), tracking no
    # slower, but with loops 2.52-2.55 -> 2.52-2.63; cabinet 2.59 / 2.11 -> 2.43 / 2.19, 7-Scenes
    # 3.68 / 3.22 -> 3.76 / 3.21
    map_reuse: bool = False  # keep trimmed local-map points in an archive and bring them back when in view again
    map_reuse_archive: int = 50000  # points kept in the archive, at most
    map_reuse_min_observations: int = 1  # a trimmed point goes to the archive only when observed at this many map updates (its first included; fewer: dropped, as ORB-SLAM culls points seen by few keyframes)
    map_reuse_each_frame: bool = True  # bring archived points back at every tracked frame (false: at map updates only)
    map_reuse_distance_ratio: float = 2.0  # an archived point comes back only seen from within [1/r, r] × its first sighting's distance ...
    map_reuse_angle: float = 60.0  # deg; ... and within this angle of its first sighting's viewing direction
    map_reuse_points: int = 0  # > 0: archived points come back only while the local map holds fewer than this (those observed most first); 0: all in view
    # Matching in ORB-SLAM's direction: each map point in view takes its nearest keypoint under
    # the ratio test against its second nearest keypoint, and a keypoint taken by several map
    # points keeps the oldest (duplicates of one surface point all find it, where the ratio test
    # among map points refuses the keypoint); off: each keypoint takes its nearest map point
    match_from_map: bool = False  # ratio test per map point over the frame's keypoints, the oldest map point kept per keypoint
    match_tile: float = 0.0  # px; > 0 with match_from_map: gated matching by projection, a map point compared only with the keypoints within guided_radius of its tile of this size; 0: with every keypoint
    map_reuse_replace: bool = False  # with match_from_map: a newer map point that took a keypoint an older one took as a PnP inlier is removed (a duplicate)
    lost_frames_reset: int = 3  # lost frames in a row before a new segment starts (Odom/ResetCountdown)


@dataclass
class KeyframeConfig:
    linear_update: float = 0.1  # metres moved since the last keyframe (RGBD/LinearUpdate)
    angular_update: float = 0.1  # radians turned since the last keyframe (RGBD/AngularUpdate)
    min_inlier_ratio: float = 0.5  # a keyframe also when inliers drop below this × the last keyframe's
    min_inliers: int = 80  # ... or below this absolute count (Odom/KeyFrameThr-like)


@dataclass
class LoopConfig:
    enabled: bool = True  # false = odometry-only baseline (mnemoslam run --odometry-only)
    threshold: float = 0.11  # hypothesis acceptance (Rtabmap/LoopThr)
    min_age: float = 10.0  # keyframes younger than this many seconds are not loop candidates (keyframes come faster than RTAB-Map's 1 Hz)
    nndr_ratio: float = 0.8  # a descriptor makes a new word unless d1 < ratio·d2 (Kp/NndrRatio)
    min_inliers: int = 20  # geometric verification (Vis/MinInliers)
    optimize_max_error: float = 3.0  # reject a link whose graph error exceeds this many σ (RGBD/OptimizeMaxError)
    proximity_by_space: bool = True  # also verify older keyframes the graph places near the new one (RGBD/ProximityBySpace)
    proximity_radius: float = 1.0  # m, camera centres at most this far apart are proximity candidates
    proximity_angle: float = 45.0  # deg, ... and optical axes at most this far apart (RGBD/ProximityAngle)
    proximity_max_candidates: int = 3  # nearest candidates verified per keyframe; the first that passes is linked
    # Links along the robot's own recent path (RGBD/ProximityByTime): each keyframe is also
    # registered to recent keyframes of its segment that see the same place (not loop
    # candidates: in the STM or younger than min_age; not its odometry neighbour). They skip
    # the drift the odometry chain accumulated in between (synthetic loop, first 900
    # frames: 0.99 -> 0.2 cm).
    proximity_by_time: bool = True  # link each keyframe to recent keyframes of its own path in view (RGBD/ProximityByTime)
    proximity_time_links: int = 2  # at most this many per keyframe: the oldest recent keyframe in view, then halfway to it
    proximity_dense: bool = True  # when PnP refuses the nearest candidate, register it densely from the graph's pose (RTAB-Map: Reg/Strategy=1)
    proximity_dense_min_overlap: float = 0.3  # share of the new keyframe's points that must be associated
    proximity_max_correction: float = 0.2  # m; the dense result may move the graph's relative pose this much ...
    proximity_max_rotation: float = 10.0  # deg; ... and turn it this much
    # Relocalization (issue 22): a keyframe whose map has joined none of the map's older ones
    # (a new session, before it joined) is searched for in them by appearance, as ORB-SLAM3's
    # Atlas does every keyframe: tf-idf of its descriptors over the older maps' nodes, in
    # working or long-term memory (their words read from the store), the best few verified
    # by PnP and the link σ check. A single verified link never joins maps: two must agree on
    # where the keyframe lies in the older map (two candidates of one keyframe, or links of
    # keyframes within relocalize_window of each other). Appearance hypotheses into an older
    # map go the same way.
    relocalize: bool = True  # search the older maps by appearance for a keyframe whose map has not joined them (ORB-SLAM3's relocalization; RTAB-Map: RGBD/AggressiveLoopThr lowers the threshold instead)
    relocalize_candidates: int = 2  # the best-scoring place's nodes verified per keyframe ...
    relocalize_places: int = 2  # ... and the best node of the next places, up to this many places (a keyframe verified at two places that disagree gives no evidence: repeated textures)
    relocalize_place_radius: float = 1.0  # m; candidates whose cameras are this close to a better one's are of its place
    relocalize_min_inliers: int = 30  # PnP inliers a relocalization link needs (loop.min_inliers for loops)
    relocalize_window: int = 3  # links of the last this many keyframes (of the same map) may agree with the new keyframe's
    relocalize_agreement: float = 0.03  # m; two links agree when they place the keyframe within this of each other ...
    relocalize_agreement_rotation: float = 2.0  # deg; ... and within this rotation
    relocalize_live: bool = True  # robots mapping at the same time relocalize against each other's keyframes too (the newer map joins the older by the same two agreeing links; in the mapping process and offline pipelines sharing a store)
    refine_dense: bool = True  # refine RGB-D loop links by dense photometric + point-to-plane registration
    refine_min_overlap: float = 0.1  # share of the new keyframe's points the registration must associate
    refine_max_correction: float = 0.1  # m; a refinement that moves the PnP link more is not used ...
    refine_max_rotation: float = 5.0  # deg; ... nor one that turns it more
    # Accurate loop / proximity links, or none (issue 12): a verified link with features is
    # re-estimated by a two-view reprojection refinement over both keyframes' matched features
    # (service/mapping/link_refinement.py); a link whose σ (Hessian at the solution × the
    # residual's variance factor) is beyond these bounds is dropped (counted: `run`'s
    # "inaccurate link(s) dropped"). Its information is the verification's noise model (PnP's
    # or the dense registration's), its σ × link_refine_sigma_factor where it takes the
    # refined transform (on TUM fr1/desk's motion capture the refined transforms are 1.4-1.8x
    # closer to the truth: bench/bench_links.py), and loosened where the refinement's
    # covariance is larger. Never the refinement's own σ alone: it sees the matched points'
    # noise, not calibration, distortion or depth bias, and is 5-20x below real links'
    # errors (issue 29: as the information it made 7-Scenes 3.20 -> 4.71 cm).
    link_refine: bool = True  # refine loop / proximity links by two-view reprojection and check their σ
    link_max_sigma_translation: float = 0.01  # m; a link whose largest translation σ is beyond this is dropped ...
    link_max_sigma_rotation: float = 0.5  # deg; ... as one whose largest rotation σ is beyond this
    link_depth_noise: float = 0.003  # each point's depth σ = this × z² (m), along its viewing ray
    # the refinement's three parts, each switchable alone (bench/bench_links.py studies them):
    link_refine_transform: bool = True  # the link takes the refined transform (a densely refined link keeps its own)
    link_refine_information: bool = True  # loosen the link's information where the refinement's covariance is larger
    link_refine_sigma_factor: float = 0.667  # a link that takes the refined transform claims the verification's σ × this
    link_refine_drop: bool = True  # a link whose σ is beyond link_max_sigma_* (or that cannot be refined) is dropped
    # ... and one whose two estimates disagree: the refinement moved the verified (PnP) transform by
    # more than this; a good link's two estimates agree within ~2 cm (TUM fr1/desk: 0.3-2.1 cm), and
    # where the verification was grossly off (10 cm / 3.8° against the motion capture) the refinement
    # started from too far and stopped half-way (4.6 cm moved, 5.9 cm off). 0 = no such check
    link_max_disagreement: float = 0.04  # m
    link_max_disagreement_rotation: float = 3.0  # deg
    process: bool = True  # service: every robot's map update in one child process (its own GIL), so a slow update never slows tracking; false = a thread of the service (offline runs are always inline)
    process_nice: int = 10  # that child's nice increment (lower CPU priority than tracking); 0 = same priority
    backlog_images: int = 30  # keyframes waiting for the map update with their images (1.6 MB each at 640x480); beyond, they go without (no dense refinement at them) so a map update that falls behind costs no more memory (issue 24)
    # Local bundle adjustment (service/mapping/local_ba.py): each keyframe's odometry link
    # becomes the relative pose a windowed BA of the newest keyframes and their shared points
    # gives (GTSAM, robust reprojection + a depth term weighted by the sensor's depth σ).
    local_ba: bool = False  # refine odometry links by local bundle adjustment (ORB-SLAM's local BA)
    local_ba_window: int = 8  # keyframes of the odometry chain in the window ...
    local_ba_fixed: int = 1  # ... of which the oldest this many are held fixed (gauge)
    local_ba_iterations: int = 10  # Levenberg-Marquardt iterations per window
    local_ba_depth_weight: float = 1.0  # × the depth term's information (σ_z = features.depth_noise·z² for RGB-D); 0 = reprojection only
    local_ba_relink: bool = True  # also replace the graph's odometry links between the window's older keyframes (they gain the points seen after them)
    local_ba_fuse: bool = True  # a keyframe feature that matches an older window point by projection and descriptor fuses the tracker's point into it (the local map re-creates points it lost: one surface point, several ids)
    local_ba_min_points: int = 30  # shared points (and observations per free keyframe) below which a window is not solved
    local_ba_max_correction: float = 0.03  # m; a BA link farther than this from the tracker's is not used ...
    local_ba_max_rotation: float = 2.0  # deg; ... nor one turned more
    local_ba_adaptive_depth: bool = True  # scale the depth σ per window by the robust spread of its residuals when > 1 (misregistered depth loses weight)


@dataclass
class MemoryConfig:
    incremental: bool = True  # false: localization only (RTAB-Map's Mem/IncrementalMemory): robots are tracked and relocalize in the stored map by appearance, their poses go out in its frame once relocalized, and nothing is written to the map (the database is opened read-only; a camera asks the same for one robot with `localize` in its camera info, `mnemoslam stream --localize`)
    localization_nodes: int = 30  # keyframes a localizing robot keeps in RAM (linked to the map's nodes, optimised with those fixed; older ones are forgotten, RGBD/MaxOdomCacheSize-like)
    stm_size: int = 10  # short-term memory: the last keyframes, not loop candidates (Mem/STMSize) ...
    max_wm_nodes: int = 0  # working memory (loop candidates in RAM) above this many nodes: the excess goes to long-term memory, the database only (Rtabmap/MemoryThr); 0 = unlimited
    time_threshold_ms: float = 0.0  # the map update's time budget (Rtabmap/TimeThr): an update over it lowers WM's limit in proportion (at most a tenth at once), updates under 0.8x it raise the limit back by one node each, up to max_wm_nodes; 0 = no budget
    recent_wm_ratio: float = 0.2  # nodes that entered WM since the last loop closure stay, up to this share of WM (Mem/RecentWmRatio)
    local_radius: float = 1.0  # m; WM nodes the graph places this near the new keyframe are not transferred either (RGBD/LocalImmunizationRatio-like)
    max_retrieved: int = 2  # LTM nodes brought back per update, around the best loop hypothesis (even below loop.threshold) and the new keyframe (Rtabmap/MaxRetrieved)
    retrieval_depth: int = 3  # ... within this many graph links of them
    retrieval_immunity: int = 10  # map updates a retrieved node stays in WM before it can be transferred (unless nothing else can go), and a transferred node stays in LTM before it can be retrieved again: no churn
    rehearsal: bool = True  # merge a keyframe into the working-memory node the map already has where it was taken (weight up) instead of adding one (RTAB-Map's rehearsal, on there too): the map grows with the place, not with time
    rehearsal_similarity: float = 0.15  # ... when they share this ratio of visual words (matched words / the larger node's words; RTAB-Map's Mem/RehearsalSimilarity is 0.6, for the same place seen again without moving: views 5-20 cm apart share 0.1-0.4 of their words on 7-Scenes) ...
    rehearsal_max_distance: float = 0.1  # m; ... and registration puts the two cameras this close (RGBD/LinearUpdate) ...
    rehearsal_max_rotation: float = 0.1  # rad; ... and turned at most this far apart (RGBD/AngularUpdate)


@dataclass
class ZenohConfig:
    mode: str = "peer"  # peer | client | router (a Python router session: no zenohd is needed)
    listen: list = field(default_factory=lambda: ["tcp/127.0.0.1:7447"])  # the service listens here
    connect: list = field(default_factory=list)  # e.g. a router's endpoint in deployments
    multicast_scouting: bool = False  # off: processes on one host must not find each other by accident
    gossip_scouting: bool = False
    shared_memory: bool = False  # zenoh shared memory from cameras on this host; off: zenoh 1.10 keeps each sender's 16 MB pool mapped after it left (issue 24)
    prefix: str = "mnemoslam"  # key expressions: <prefix>/<robot>/camera/frame, .../pose, ...


@dataclass
class ServiceConfig:
    queue_size: int = 30  # frames waiting per robot (1 s at 30 Hz); when full the oldest is dropped (and counted) ...
    queue_mb: float = 128.0  # ... also when their decoded images would exceed this many MB
    info_timeout: float = 2.0  # s to wait for a camera's info reply; a robot is asked again at most this often
    hold_frames: int = 2  # newest frames of a robot without a slot kept (undecoded) until its info arrives; 0: none
    max_message_mb: float = 32.0  # frame messages larger than this are rejected before decoding
    max_image_side: int = 4096  # px; larger claimed sizes are rejected before decoding
    max_robots: int = 32  # robot slots; a robot gets one when its camera info arrives, frames of others are rejected
    idle_timeout: float = 60.0  # s without frames after which a robot's slot is freed (its session ends)
    malloc_trim_s: float = 10.0  # s between malloc_trim(0) calls: glibc gives the freed frame buffers' pages back (issue 24); 0: never
    restart_gap: float = 5.0  # s; a frame whose stamp is this much older than the robot's last is a camera (clock) restart: its session ends ("restarted") and a new one starts; smaller steps back are refused (stamp_order); 0 = never


@dataclass
class StorageConfig:
    path: str = "mnemoslam.db"  # the SQLite long-term memory
    keep_images: bool = True  # store each keyframe's JPEG colour and PNG-16 depth (Mem/BinDataKept)
    jpeg_quality: int = 90


@dataclass
class ApiConfig:
    enabled: bool = True
    host: str = "127.0.0.1"
    port: int = 8080
    token: str = ""  # bearer token the endpoints that change the map need (env MNEMOSLAM_API_TOKEN overrides); "" = those endpoints answer 403
    protect_reads: bool = False  # true: every endpoint but /health needs the token too (then a token must be set)


@dataclass
class SemanticsConfig:
    enabled: bool = True  # fuse semantic labels of keyframes into 3-D objects with class histograms (issues 14, 24)
    source: str = "auto"  # auto (the camera's labels when a frame carries them, else the ONNX model below when it is found) | model (always the model) | camera (only labels sent with the frames)
    model: str = "deeplabv3_mnv2_ade20k32.onnx"  # file name under MNEMOSLAM_MODELS (default ../shared/models next to the repository) or a path
    model_input: str = "MobilenetV2/MobilenetV2/input"  # the model adapter: input tensor name ...
    model_size: int = 512  # ... square input side (px): the longer image side is resized to it, the rest padded ...
    model_pad: int = 127  # ... with this grey value (uint8)
    model_layout: str = "nhwc"  # nhwc | nchw input layout
    model_dtype: str = "uint8"  # uint8 (raw 0..255) | float32 (scaled by model_scale after subtracting model_mean)
    model_mean: float = 0.0  # float32 inputs: (pixel - mean) * scale
    model_scale: float = 1.0
    model_output: str = "argmax"  # argmax (int label map 1×S×S) | scores (1×K×S×S or 1×S×S×K class scores) | boxes (a detection model: box, score and class outputs) | yolo (one 1×(4+K)×N or 1×N×(4+K) output: cx, cy, w, h, K class scores)
    box_outputs: list = field(default_factory=lambda: ["boxes", "scores", "classes"])  # boxes: the detection model's output names (N×4 boxes, N scores, N class ids; a leading batch axis is fine)
    box_format: str = "xyxy"  # boxes (yolo: always cxcywh): xyxy | yxyx (TF Object Detection API) | cxcywh
    box_normalized: bool = False  # boxes: coordinates in 0..1 of the model input (else its pixels)
    class_offset: int = 0  # detection class ids + this = ids into `classes` (e.g. -1 for models counting from 1)
    min_score: float = 0.5  # detections scoring lower are ignored
    nms_iou: float = 0.5  # yolo: boxes overlapping a better one by this IoU are suppressed
    box_depth_band: float = 0.15  # a box labels only its pixels whose depth is within this share of the box centre's median depth (the object, not the wall behind it); 0 = the whole box
    classes: list = field(default_factory=list)  # the model's class names by id; empty = ADE20K-32 (service/semantics/classes.py)
    threads: int = 1  # onnxruntime intra-op threads (must not steal the tracking core)
    queue_size: int = 4  # keyframes waiting for the semantic worker; when full the newest waits in the store for the back-fill (counted as deferred)
    backfill: bool = True  # segment the keyframes the worker could not take (and any of the map not segmented yet) later, newest first, from their stored images (storage.keep_images) with the model, when the queue is empty
    idle_after: float = 2.0  # s without a new keyframe after which the robots count as idle: the worker then back-fills without resting (max_duty applies while they map)
    nice: int = 10  # the semantic worker thread's nice increment (lower CPU priority than tracking); 0 = same priority
    yield_queue: int = 4  # tracking first (issue 24): in the service the worker starts a step (model run, fusion; live or back-fill) only while every robot's frame queue (service.queue_size) holds at most this many frames ...
    min_slack: float = 0.2  # ... and each robot's tracking was idle at least this share of the last second (its frame-time margin; 0 = the queue alone decides); else it waits, and the keyframes that come meanwhile wait in the store for the back-fill ...
    max_wait: float = 5.0  # ... but a keyframe that waited this many seconds for the margin goes on without it (the queue still decides): at least one live keyframe every few seconds while tracking is saturated; 0 = no bound
    preload: bool = True  # source auto: load the model when the service starts (on the worker's thread, before any robot streams), not on the first keyframe that needs it
    max_duty: float = 0.5  # the semantic worker rests after each keyframe so that it is busy at most this share of the time (on 2 cores it slows tracking in proportion; keyframes that arrive meanwhile queue, then wait for the back-fill); 1 = no rest
    dynamic: list = field(default_factory=lambda: ["person", "car"])  # classes that move (people, animals, vehicles: of ADE20K-32 person and car; name other tables' own, e.g. bus, dog): their segments never become objects, nor vote in one; a keyframe showing one counts in the worker's `dynamic`; [] = they map like any thing
    ignore: list = field(default_factory=lambda: ["other", "wall", "building", "sky", "floor", "ceiling", "road", "grass", "sidewalk", "earth", "mountain", "water", "sea", "field", "rug"])  # classes that never become objects ("stuff": surfaces without an extent)
    stride: int = 4  # label / depth pixels used: every stride-th of each row and column
    min_depth: float = 0.3  # m; labelled pixels with depth outside [min, max] are not used
    max_depth: float = 10.0  # (objects are often seen from afar: the synthetic scene's doors at 6-7.5 m median)
    min_pixels: int = 400  # a segment (connected pixels of one class) needs this many full-resolution pixels with depth
    depth_jump: float = 0.05  # neighbouring pixels whose depths differ by more than this × depth split segments
    voxel: float = 0.08  # m; objects keep their surface as voxels of this size (in the anchor's frame): centroid and extent come from them
    max_extent: float = 4.0  # m; a segment (or an object) larger than this along any axis is not an object
    min_overlap: float = 0.25  # a segment joins the object whose voxels hold this share of its voxels (any class: the histogram decides)
    min_object_share: float = 0.1  # ... and covers at least this share of the object's voxels (a painting does not join a large wall-sized object)
    stuff_cover: float = 0.5  # an ignored-class segment (wall, floor) covering this share of an object's voxels, or lying inside it by this share, votes for its class
    merge_overlap: float = 0.5  # two objects sharing this share of the smaller one's voxels are one object (merged)
    label_probability: float = 0.6  # p of the Bayesian update: the observed class gets p, every other (1 - p) / (K - 1) (Kimera, SemanticFusion)
    min_probability: float = 1e-4  # histogram floor after each update, so old evidence can still be overturned
    min_observations: int = 3  # keyframes that must see an object before it is stored (one noisy frame makes no object)


@dataclass
class RosConfig:
    enabled: bool = False  # accept ROS 2 camera topics bridged to Zenoh (zenoh-bridge-ros2dds / rmw_zenoh: CDR Image, CompressedImage, CameraInfo) for the robots below (service/ros.py)
    robots: list = field(default_factory=list)  # one mapping per robot: {robot: r1, color: KEY, depth: KEY, info: KEY, pose: KEY, intrinsics: k}; KEY = the topic's Zenoh key (the bridge's: the topic without its leading '/'); depth registered to colour; pose (PoseStamped out), intrinsics (k, or p for image_rect topics), localize (true: localization only for that robot), imu (KEY of sensor_msgs/Imu: each frame's accelerometer reading, the occupancy grid's up) and imu_axes (optical | body | A:B:C, the IMU's axes in the camera's; default by the Imu's frame name) optional
    frame_id: str = "map"  # header.frame_id of the PoseStamped poses published on a robot's pose key
    sync_tolerance: float = 0.015  # s; a colour and a depth image pair when their header stamps differ by at most this (the nearest)
    sync_window: float = 0.5  # s; an unpaired image waits for its partner until its own stream is this far past it (the other stream's callbacks may lag), then is dropped (counted unpaired)
    sync_queue: int = 16  # ... and at most this many unpaired images wait per stream (memory: raw 640×480 colour is 0.9 MB each); older ones are dropped (counted unpaired)


@dataclass
class GridConfig:
    enabled: bool = True  # a local occupancy grid per RGB-D keyframe from its depth, stored with the node (RTAB-Map: Grid/FromDepth); the map's grid, cloud and paths are built from them (docs/grid.md)
    cell_size: float = 0.05  # m, the local grids' cells and the map grid's default resolution (Grid/CellSize)
    depth_decimation: int = 4  # every n-th depth pixel of each row and column (Grid/DepthDecimation)
    range_min: float = 0.0  # m; depth points nearer than this are not used (Grid/RangeMin)
    range_max: float = 5.0  # m; ... nor farther than this (Grid/RangeMax)
    ray_tracing: bool = True  # cells between the camera and what it sees are free (Grid/RayTracing; false in RTAB-Map, whose free space is only the floor it sees)
    max_ground_height: float = 0.05  # m above the floor: points lower are floor (free) (Grid/MaxGroundHeight; 0 = off there)
    max_obstacle_height: float = 1.9  # m above the floor: points higher (ceilings, lamps) are ignored (Grid/MaxObstacleHeight; 0 = off there)
    max_ground_angle: float = 45.0  # deg; depth points whose surface normal is this close to the expected up are floor candidates, and the fitted floor may turn this far from it (Grid/MaxGroundAngle)
    floor_min_points: int = 150  # decimated depth points within ±floor_band of a plane for it to count as the floor
    floor_band: float = 0.03  # m, half thickness of the floor slab of the plane fit
    up: list = field(default_factory=lambda: [0.0, -1.0, 0.0])  # the camera mounting: the up direction in the camera frame (x right, y down, z forward) before a floor or an accelerometer says otherwise
    camera_height: float = 1.2  # m, the camera above the floor until a floor is seen (a handheld camera: ~1.2-1.5)
    frame_nodes: int = 50  # the map grid's plane is perpendicular to the mean up of the map's oldest this many keyframes whose up came from a floor or an accelerometer (not the configured mounting)
    prob_hit: float = 0.7  # an obstacle cell of a keyframe adds logodds(prob_hit) (GridGlobal/ProbHit)
    prob_miss: float = 0.4  # a free cell adds logodds(prob_miss) (GridGlobal/ProbMiss)
    prob_clamping_min: float = 0.1192  # the cell's probability is clamped to [min, max] (GridGlobal/ProbClampingMin)
    prob_clamping_max: float = 0.971  # (GridGlobal/ProbClampingMax)
    occupancy_thr: float = 0.5  # a cell is occupied above this probability (GridGlobal/OccupancyThr)
    update_error: float = 0.01  # m; a keyframe whose optimised pose moved more (or turned more than this / 1 m in rad) is re-placed in the map grid (GridGlobal/UpdateError); 0 = at any change
    refresh_interval: float = 1.0  # s; a map's grid asked for over REST is kept up to date by a thread of the API, a pass this often while it is asked for (within 60 s) and one at each request, so a request does not pay a loop closure's re-assembly; 0 = every request assembles (docs/grid.md)
    max_wait: float = 0.1  # s; a request waits this long for the grid to be brought up to date, then gets the last one assembled (header X-Map-Current: false)
    cloud_cache_mb: int = 256  # MiB; GET /maps/{map}/cloud keeps each keyframe's filtered points (by pose and voxel) and the last whole cloud within this, so a second request does not decode every keyframe's images again; 0 = no cache
    footprint_radius: float = 0.2  # m; the cells this close to a keyframe's position are free: the camera (the robot, the person holding it) was there (GridGlobal/FootprintRadius, 0 there); 0 = off
    robot_radius: float = 0.2  # m; paths (GET /path) keep this far from occupied cells
    path_unknown: bool = False  # paths may cross unknown cells (else free cells only)


@dataclass
class Config:
    features: FeatureConfig = field(default_factory=FeatureConfig)
    stereo: StereoConfig = field(default_factory=StereoConfig)
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    keyframe: KeyframeConfig = field(default_factory=KeyframeConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    memory: MemoryConfig = field(default_factory=MemoryConfig)
    zenoh: ZenohConfig = field(default_factory=ZenohConfig)
    service: ServiceConfig = field(default_factory=ServiceConfig)
    storage: StorageConfig = field(default_factory=StorageConfig)
    api: ApiConfig = field(default_factory=ApiConfig)
    semantics: SemanticsConfig = field(default_factory=SemanticsConfig)
    ros: RosConfig = field(default_factory=RosConfig)
    grid: GridConfig = field(default_factory=GridConfig)
    seed: int = 0  # seeds every random choice (RANSAC), for bit-for-bit reproducible runs


class ConfigError(ValueError):
    pass


def _build(cls, data: dict, where: str):
    if not isinstance(data, dict):
        raise ConfigError(f"{where.rstrip('.') or 'config'}: expected a mapping (a config section), got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    kwargs = {}
    for key, value in data.items():
        if key not in names:
            raise ConfigError(f"unknown config key {where + key!r}; known: {', '.join(sorted(names))}")
        typ = hints[key]
        if dataclasses.is_dataclass(typ):
            kwargs[key] = _build(typ, {} if value is None else value, f"{where}{key}.")
        else:
            kwargs[key] = _coerce(typ, value, where + key)
    return cls(**kwargs)


def _coerce(typ, value, name):
    origin = typing.get_origin(typ)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(typ)
        if value is None and type(None) in args:
            return None
        typ = next(a for a in args if a is not type(None))
    if typ is float and isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if typ in (int, str, bool) and type(value) is typ:
        return value
    if (typ in (list, tuple) or typing.get_origin(typ) in (list, tuple)) and isinstance(value, list):
        return list(value)
    raise ConfigError(f"config key {name!r}: expected {getattr(typ, '__name__', typ)}, got {value!r}")


def load_config(path: str | Path | None = None, overrides: dict | None = None) -> Config:
    """Defaults, updated by a YAML file, then by `overrides` (same nested shape)."""
    data: dict = {}
    if path is not None:
        try:
            data = yaml.safe_load(Path(path).read_text()) or {}
        except OSError as e:
            raise ConfigError(f"cannot read config {path}: {e.strerror}") from None
        except yaml.YAMLError as e:
            raise ConfigError(f"{path}: invalid YAML: {e}") from None
    if overrides:
        data = merge_overrides(data, overrides)
    return _build(Config, data, "")


def parse_sets(items: list[str] | tuple[str, ...] | None) -> dict:
    """`--set KEY=VALUE` items as `load_config` overrides: KEY is a dotted path into the
    config (`loop.enabled`, `service.queue_size`, `seed`), VALUE a YAML scalar or flow list
    (`false`, `30`, `0.5`, `[tcp/127.0.0.1:7447]`). Later items win. Only the form is checked
    here (ConfigError); `load_config` rejects unknown keys and wrongly typed values."""
    out: dict = {}
    for item in items or ():
        key, eq, text = item.partition("=")
        path = key.strip().split(".")
        if not eq or not all(path):
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE with a dotted KEY, e.g. loop.enabled=false")
        try:
            value = yaml.safe_load(text)
        except yaml.YAMLError as e:
            raise ConfigError(f"--set {key}: VALUE {text!r} is not valid YAML ({str(e).splitlines()[0]})") from None
        if isinstance(value, dict):
            raise ConfigError(f"--set {key}: VALUE must be a scalar or a list; set the keys of a section one by one "
                              f"({key}.NAME=VALUE)")
        node = out
        for i, part in enumerate(path[:-1]):
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"--set {key}: {'.'.join(path[:i + 1])} is set to a value by another --set")
        if isinstance(node.get(path[-1]), dict):
            raise ConfigError(f"--set {key}: other --set items set keys inside it")
        node[path[-1]] = value
    return out


def merge_overrides(a: dict, b: dict) -> dict:
    """`a` updated by `b`, nested mappings merged key by key (neither is modified)."""
    out = dict(a)
    for k, v in b.items():
        out[k] = merge_overrides(out[k] if isinstance(out.get(k), dict) else {}, v) if isinstance(v, dict) else v
    return out


def to_dict(config: Config) -> dict:
    """The config as plain data, as shown (REST /config) and stored with each session: the API
    token is never included (a set token shows as "***")."""
    d = dataclasses.asdict(config)
    if d.get("api", {}).get("token"):
        d["api"]["token"] = "***"
    return d


def default_yaml() -> str:
    """Every key with its default and its comment from this module, as `configs/default.yaml`
    holds it (`mnemoslam config` prints it; a test keeps the file equal to it)."""
    import inspect
    import re
    import sys

    source = inspect.getsource(sys.modules[__name__])
    out = ["# mnemoslam default configuration: every key with its default value.",
           "# A config file only needs the keys it changes; names follow RTAB-Map's parameters where one exists.",
           "# Generated by `mnemoslam config` from service/config.py.", ""]
    config = Config()
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if not dataclasses.is_dataclass(value):
            out.append(f"{f.name}: {value}")
            continue
        body = source[source.index(f"class {type(value).__name__}:"):]
        body = body[: body.find("\n\n\n")] if "\n\n\n" in body else body
        out.append(f"{f.name}:")
        for g in dataclasses.fields(value):
            m = re.search(rf"^\s+{g.name}: .*?(#.*)?$", body, re.MULTILINE)
            comment = f"  {m.group(1)}" if m and m.group(1) else ""
            out.append(f"  {g.name}: {yaml.safe_dump(getattr(value, g.name), default_flow_style=True, width=10**6).strip().removesuffix('...').strip()}{comment}")
        out.append("")
    return "\n".join(out) + "\n"
