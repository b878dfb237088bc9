"""Ground truth: Snell's-law ray tracing through real lenses, rigs, scenes and images."""

from ._gauges import (
    BEARING_RADII_MM as BEARING_RADII_MM,
    RING_GAUGE_RADIUS_MM as RING_GAUGE_RADIUS_MM,
    GaugeScan as GaugeScan,
    ScanFrame as ScanFrame,
    StepProfile as StepProfile,
    default_stage as default_stage,
    gauge_scan as gauge_scan,
    step_gauge as step_gauge,
)
from ._glass import (
    GLASSES as GLASSES,
    Glass as Glass,
    glass_index as glass_index,
    known_glasses as known_glasses,
)
from ._images import write_scene_images as write_scene_images
from ._lens import (
    Lens as Lens,
    Paraxial as Paraxial,
    lens_from_dict as lens_from_dict,
    load_lens as load_lens,
    paraxial as paraxial,
    read_lens as read_lens,
    resolve_lens as resolve_lens,
    shipped_lenses as shipped_lenses,
)
from ._observe import (
    Truth as Truth,
    nominal_of as nominal_of,
    read_truth as read_truth,
    simulate_observations as simulate_observations,
    truth_from_dict as truth_from_dict,
    truth_to_dict as truth_to_dict,
    write_truth as write_truth,
)
from ._pupil import (
    PupilImage as PupilImage,
    PupilSampling as PupilSampling,
    pupil_grid as pupil_grid,
    pupil_image as pupil_image,
    pupil_points as pupil_points,
)
from ._render_board import (
    BoardMap as BoardMap,
    board_map as board_map,
    render_checkerboard as render_checkerboard,
    rig_board_maps as rig_board_maps,
)
from ._render_capture import (
    CaptureTruth as CaptureTruth,
    StripeScore as StripeScore,
    board_view_capture as board_view_capture,
    homography_map as homography_map,
    render_capture as render_capture,
    score_stripe as score_stripe,
)
from ._render_stripe import StripeTruth as StripeTruth, render_stripe as render_stripe
from ._rig import (
    Rig as Rig,
    Spot as Spot,
    build_rig as build_rig,
    laser_plane_from_angles as laser_plane_from_angles,
    paper_rig as paper_rig,
    paraxial_sensor_pose as paraxial_sensor_pose,
)
from ._scenes import (
    BoardView as BoardView,
    StripeProfile as StripeProfile,
    board_poses as board_poses,
    stripe_on_board as stripe_on_board,
    trace_points as trace_points,
)
from ._stage_target import (
    StageTargetScan as StageTargetScan,
    lying_target_pose as lying_target_pose,
    stage_target_lines as stage_target_lines,
    stage_target_scan as stage_target_scan,
    write_stage_target_images as write_stage_target_images,
)
from ._trace import (
    Surfaces as Surfaces,
    Trace as Trace,
    aim_ray as aim_ray,
    intersect_plane as intersect_plane,
    intersect_surface as intersect_surface,
    refract as refract,
    sensor_normal as sensor_normal,
    sensor_rotation as sensor_rotation,
    trace as trace,
)
