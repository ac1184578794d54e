"""The synthetic generator's stages, alone: the scene of a frame and its laser labels agree with the agents."""
import numpy as np
from waymo_open_dataset import dataset_pb2

from ff3d_tf.data.synthetic import wod as synthetic
from ff3d_tf.data.synthetic import scene as sim


def test_laser_labels_are_the_agents_in_the_vehicle_frame():
    rng = np.random.default_rng(3)
    ego_speed = 6.0
    road, agents = sim.make_scene(rng, ego_speed)
    scene = sim.frame_scene(5, 0.5, road, agents, ego_speed)
    assert scene.labelled_now, "the scene should have labelled agents near the ego vehicle"
    frame = dataset_pb2.Frame()
    synthetic._laser_labels(frame, scene, road, "seg", {})
    assert len(frame.laser_labels) == len(scene.labelled_now)
    by_id = {a.track_id: a for a in scene.near}
    vehicle_from_world = np.linalg.inv(scene.pose)[:3, :3]
    turning = 0
    for label in frame.laser_labels:
        agent = by_id[label.id.split("seg_", 1)[1]]
        centre_v = np.array([label.box.center_x, label.box.center_y, label.box.center_z, 1.0])
        centre_w = scene.pose @ centre_v  # vehicle -> world must give back the agent's world centre
        np.testing.assert_allclose(centre_w[:3], scene.poses_t[agent.track_id][0], atol=1e-9)
        # Speed: the box centre's displacement over the last 0.1 s, in the vehicle frame; acceleration: the change of
        # that speed from the frame before (what Waymo's v2 converter requires besides speed).
        c = [agent.pose(road, 0.5 - k * sim.DT_S)[0] for k in range(3)]
        v_w, v_prev_w = (c[0] - c[1]) / sim.DT_S, (c[1] - c[2]) / sim.DT_S
        np.testing.assert_allclose([label.metadata.speed_x, label.metadata.speed_y], (vehicle_from_world @ v_w)[:2],
                                   atol=1e-9)
        assert label.metadata.HasField("accel_x") and label.metadata.HasField("accel_y")
        accel_v = vehicle_from_world @ ((v_w - v_prev_w) / sim.DT_S)
        np.testing.assert_allclose([label.metadata.accel_x, label.metadata.accel_y], accel_v[:2], atol=1e-6)
        assert label.type == agent.class_id
        turning += agent.speed != 0 and np.hypot(label.metadata.accel_x, label.metadata.accel_y) > 0.05
    assert turning, "agents moving on the curved road should accelerate"

