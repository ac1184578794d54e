"""The Argoverse 2 challenge protocol (ff3d_tf.metrics_av2) against hand calculations and, on the real sample log,
against a straight-line NumPy reference of the community evaluator's arithmetic (bucketed_scene_flow_eval)."""
import os

import numpy as np
import pytest

from ff3d_tf import metrics_av2 as m
from ff3d_tf import schema

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
AV2_LOG = os.path.join(ROOT, "data", "av2_sample_log")
CAR, PED, SIGN, NONE = (int(m.label_index(n)) for n in ("REGULAR_VEHICLE", "PEDESTRIAN", "SIGN", "NONE"))


def _flows(speeds, axis=0):
    f = np.zeros((len(speeds), 3))
    f[:, axis] = speeds
    return f


# --- categories and mappings ----------------------------------------------------------------------------------------

def test_categories_follow_av2_api_index_order():
    assert len(m.AV2_CATEGORIES) == 30 and len(set(m.AV2_CATEGORIES)) == 30
    assert list(m.AV2_CATEGORIES) == sorted(m.AV2_CATEGORIES)  # av2-api's enum is alphabetical
    # av2-api CATEGORY_TO_INDEX: NONE 0, then enum order from 1.
    assert m.label_index(["NONE", "ANIMAL", "REGULAR_VEHICLE", "WHEELED_RIDER", ""]).tolist() == [0, 1, 19, 30, 0]
    with pytest.raises(ValueError, match="'CAR' is not an Argoverse 2 category"):
        m.label_index(["CAR"])
    from ff3d_tf.data.av2 import argoverse2  # the reader's per-name lookup agrees
    assert m.label_index(m.AV2_CATEGORIES).tolist() == [argoverse2.scene_flow_category_index(c)
                                                        for c in m.AV2_CATEGORIES]


def test_sample_log_labels_use_the_one_based_index():
    # The `classes` column of the sample's flow labels names exactly categories annotated at sweep 0 when read with
    # NONE = 0 and categories from 1 (read 0-based, index 6 would be BUS, which the log does not have).
    import pyarrow.feather as feather
    from ff3d_tf.data.av2 import argoverse2
    labels = set(np.unique(feather.read_table(os.path.join(AV2_LOG, "flow_labels.feather")).column("classes")
                           .to_numpy()).tolist()) - {0}
    ann = feather.read_table(os.path.join(AV2_LOG, "annotations.feather"))
    t0 = argoverse2.sweep_timestamps(AV2_LOG)[0]
    at_t0 = ann.column("timestamp_ns").to_numpy() == t0
    cats = set(np.asarray(ann.column("category").to_numpy(zero_copy_only=False))[at_t0].tolist())
    assert labels <= set(m.label_index(sorted(cats)).tolist())
    assert {m.LABEL_NAMES[i] for i in labels} >= {"REGULAR_VEHICLE", "PEDESTRIAN", "BICYCLE", "BOX_TRUCK"}


def test_meta_classes_are_the_evaluators():
    assert m.META_CLASSES == ("BACKGROUND", "CAR", "OTHER_VEHICLES", "PEDESTRIAN", "WHEELED_VRU")  # sorted
    sizes = {k: len(v) for k, v in m.META_CLASS_CATEGORIES.items()}
    assert sizes == {"BACKGROUND": 1, "CAR": 1, "OTHER_VEHICLES": 9, "PEDESTRIAN": 4, "WHEELED_VRU": 6}
    # The rest: 8 road signs / sign trailers ("labelling oddities") and the two animal categories.
    assert set(m.IGNORED_CATEGORIES) == {"BOLLARD", "CONSTRUCTION_BARREL", "CONSTRUCTION_CONE", "SIGN", "STOP_SIGN",
                                         "MOBILE_PEDESTRIAN_CROSSING_SIGN", "MESSAGE_BOARD_TRAILER",
                                         "TRAFFIC_LIGHT_TRAILER", "ANIMAL", "DOG"}
    every = [c for v in m.META_CLASS_CATEGORIES.values() for c in v] + list(m.IGNORED_CATEGORIES)
    assert sorted(every) == sorted(m.LABEL_NAMES)  # each label in exactly one place
    assert m.META_OF_LABEL[[NONE, CAR, PED, SIGN]].tolist() == [0, 1, 3, -1]
    assert m.META_OF_LABEL[m.label_index("WHEELED_DEVICE")] == m.META_CLASSES.index("WHEELED_VRU")


def test_paper_classes_come_from_the_readers_mapping():
    from ff3d_tf.data.av2.argoverse2 import AV2_CLASS
    assert set(AV2_CLASS) <= set(m.AV2_CATEGORIES)  # the reader's mapping names real categories only
    got = {n: int(m.PAPER_CLASS_OF_LABEL[m.label_index(n)]) for n in
           ("NONE", "REGULAR_VEHICLE", "BUS", "PEDESTRIAN", "BICYCLIST", "SIGN", "WHEELED_DEVICE", "DOG")}
    assert got == {"NONE": schema.CLASS_BACKGROUND, "REGULAR_VEHICLE": schema.CLASS_VEHICLE,
                   "BUS": schema.CLASS_VEHICLE, "PEDESTRIAN": schema.CLASS_PEDESTRIAN,
                   "BICYCLIST": schema.CLASS_CYCLIST, "SIGN": schema.CLASS_SIGN,
                   "WHEELED_DEVICE": schema.CLASS_BACKGROUND, "DOG": schema.CLASS_BACKGROUND}


def test_category_mapping_table():
    lines = m.category_mapping_table().splitlines()
    assert len(lines) == 2 + 31
    assert "| 19 | REGULAR_VEHICLE | CAR | foreground | vehicle |" in lines
    assert "| 21 | SIGN | (ignored) | (ignored) | sign |" in lines
    assert "| 0 | NONE | BACKGROUND | background | background |" in lines


# --- thresholds, buckets, mask ---------------------------------------------------------------------------------------

def test_thresholds_match_the_paper_threshold():
    assert m.DYNAMIC_THRESHOLD_M == schema.MOVING_THRESHOLD_MPS * 0.1 == 0.05
    assert m.NUM_BUCKETS == 51 and len(m.BUCKET_EDGES_M) == 52
    assert m.BUCKET_EDGES_M[0] == 0.0 and m.BUCKET_EDGES_M[1] == 0.04 and m.BUCKET_EDGES_M[50] == 2.0
    assert np.isinf(m.BUCKET_EDGES_M[51])
    np.testing.assert_allclose(np.diff(m.BUCKET_EDGES_M[:51]), 0.04, rtol=1e-12)


def test_every_bucket_edge_opens_its_bucket():
    edges = m.BUCKET_EDGES_M[:51]
    # A speed equal to edge k is in bucket k (lo <= speed < hi); the float just below it is in bucket k - 1.
    assert m.speed_bucket(edges).tolist() == list(range(51))
    below = np.nextafter(edges[1:], 0.0)
    assert m.speed_bucket(below).tolist() == list(range(50))
    assert m.speed_bucket([0.0, 0.039, 1.99, 2.0, 1e6]).tolist() == [0, 0, 49, 50, 50]


def test_is_dynamic_threshold_is_inclusive():
    f = _flows([0.05, np.nextafter(0.05, 0.0), 0.0, 0.3])
    assert m.is_dynamic(f).tolist() == [True, False, False, True]


def test_eval_mask_by_hand():
    p = np.array([[34.99, 0, 0], [35.0, 0, 0], [0, -35.0, 0], [-34.99, 34.99, 0], [10, 10, 0], [1, 1, 3.0],
                  [1, 1, -2.5]])
    ground = np.array([False, False, False, False, True, False, False])
    # max(|x|, |y|) < 35 strictly (the evaluator), ground out; z only with a range (exclusive, as the loader).
    assert m.eval_mask(p, ground).tolist() == [True, False, False, True, False, True, True]
    assert m.eval_mask(p, ground, z_range_m=m.COMMUNITY_Z_RANGE_M).tolist() == [True, False, False, True, False,
                                                                                 False, False]
    with pytest.raises(ValueError, match="is_ground: .* expected bool"):
        m.eval_mask(p, ground.astype(int))
    with pytest.raises(ValueError, match="points_xyz: non-finite value at row 2"):
        m.eval_mask(np.where(np.arange(7)[:, None] == 2, np.nan, p), ground)


# --- the arithmetic by hand ------------------------------------------------------------------------------------------

def _hand_case():
    """CAR: one point at each bucket edge e_k = 0.04 k (k = 0..50), each predicted 0.01 m off (EPE 0.01).
    PEDESTRIAN: two points in bucket 3 [0.12, 0.16): speeds 0.13 and 0.15, EPEs 0.02 and 0.04.
    BACKGROUND: three still points, EPEs 0.001, 0.002, 0.003. SIGN (ignored): one point, EPE 5 m."""
    e = m.BUCKET_EDGES_M[:51]
    true = np.concatenate([_flows(e), _flows([0.13, 0.15], 1), np.zeros((3, 3)), np.zeros((1, 3))])
    pred = true.copy()
    pred[:51, 1] += 0.01
    pred[51:53, 2] += [0.02, 0.04]
    pred[53:56, 0] += [0.001, 0.002, 0.003]
    pred[56, 0] += 5.0
    label = np.array([CAR] * 51 + [PED] * 2 + [NONE] * 3 + [SIGN])
    return true, pred, label


def test_bucketed_normalized_epe_by_hand():
    acc = m.AV2FlowAccumulator()
    assert acc.update(*_hand_case()) == 57
    r = acc.result()
    # CAR static: bucket 0 holds the speed-0 point, EPE 0.01.
    assert r["bucketed/CAR/static_epe_m"] == pytest.approx(0.01, abs=1e-12)
    # CAR dynamic: buckets 1..50 hold one point each, 0.01 / (0.04 k); mean over k = 0.25 * H_50 / 50 with the
    # harmonic number H_50 = 4.499205338329425 -> 0.022496026691647.
    assert r["bucketed/CAR/dynamic_norm_epe"] == pytest.approx(0.25 * 4.499205338329425 / 50, rel=1e-9)
    assert (r["bucketed/CAR/static_count"], r["bucketed/CAR/dynamic_count"]) == (1, 50)
    # PEDESTRIAN: ratio of means (0.03 / 0.14 = 0.2142857), not the mean of ratios (0.2102564); no static points.
    assert r["bucketed/PEDESTRIAN/dynamic_norm_epe"] == pytest.approx(0.03 / 0.14, rel=1e-9)
    assert np.isnan(r["bucketed/PEDESTRIAN/static_epe_m"])
    # BACKGROUND: static 0.002, no dynamic bucket -> NaN. Classes without points: NaN, never 0.
    assert r["bucketed/BACKGROUND/static_epe_m"] == pytest.approx(0.002, abs=1e-12)
    assert np.isnan(r["bucketed/BACKGROUND/dynamic_norm_epe"])
    for meta in ("OTHER_VEHICLES", "WHEELED_VRU"):
        assert np.isnan(r[f"bucketed/{meta}/static_epe_m"]) and np.isnan(r[f"bucketed/{meta}/dynamic_norm_epe"])
    # Means over the meta-classes, NaN skipped: static (0.002 + 0.01) / 2; dynamic (0.0224960 + 0.2142857) / 2.
    assert r["bucketed/mean_static_epe_m"] == pytest.approx(0.006, abs=1e-12)
    assert r["bucketed/mean_dynamic_norm_epe"] == pytest.approx((0.25 * 4.499205338329425 / 50 + 0.03 / 0.14) / 2,
                                                                rel=1e-9)
    assert r["num_points"] == 57  # the SIGN point is counted as seen, but in no table


def test_three_way_epe_by_hand():
    r = m.AV2FlowAccumulator()
    r.update(*_hand_case())
    r = r.result()
    # Foreground = CAR + PEDESTRIAN. Static (< 0.05): CAR speeds 0 and 0.04, EPE 0.01 each.
    assert (r["three_way/fg_static_epe_m"], r["three_way/fg_static_count"]) == (pytest.approx(0.01), 2)
    # Dynamic: 49 CAR points (0.08 .. 2.0) at 0.01 and the pedestrians' 0.02, 0.04: (0.49 + 0.06) / 51.
    assert r["three_way/fg_dynamic_epe_m"] == pytest.approx(0.55 / 51, rel=1e-9)
    assert r["three_way/fg_dynamic_count"] == 51
    assert r["three_way/bg_static_epe_m"] == pytest.approx(0.002, abs=1e-12)
    assert np.isnan(r["three_way/bg_dynamic_epe_m"]) and r["three_way/bg_dynamic_count"] == 0
    assert r["three_way/mean_epe_m"] == pytest.approx((0.55 / 51 + 0.01 + 0.002) / 3, rel=1e-9)


def test_three_way_edge_and_empty_cell():
    acc = m.AV2FlowAccumulator()
    true = _flows([0.05, np.nextafter(0.05, 0.0)])
    acc.update(true, true + [0.0, 0.0, 0.1], np.array([CAR, CAR]))
    r = acc.result()
    assert r["three_way/fg_dynamic_count"] == 1 and r["three_way/fg_static_count"] == 1
    # No background points: bg static is NaN and so is the plain mean of the three (av2-api's average).
    assert np.isnan(r["three_way/bg_static_epe_m"]) and np.isnan(r["three_way/mean_epe_m"])


def test_sweeps_are_weighted_by_their_point_counts():
    # Sweep 1: one still CAR point, EPE 0.1; sweep 2: three, EPE 0.2. The evaluator weights sweeps by counts:
    # (0.1 + 3 * 0.2) / 4 = 0.175 (not the mean of sweep means, 0.15).
    acc = m.AV2FlowAccumulator()
    acc.update(np.zeros((1, 3)), _flows([0.1]), np.array([CAR]))
    acc.update(np.zeros((3, 3)), _flows([0.2] * 3), np.array([CAR] * 3))
    assert acc.result()["bucketed/CAR/static_epe_m"] == pytest.approx(0.175, abs=1e-12)
    assert acc.num_sweeps == 2


def test_streaming_merge_and_state_equal_one_pass():
    true, pred, label = _hand_case()
    whole = m.AV2FlowAccumulator()
    whole.update(true, pred, label)
    a, b = m.AV2FlowAccumulator(), m.AV2FlowAccumulator()
    a.update(true[:20], pred[:20], label[:20])
    b.update(true[20:], pred[20:], label[20:])
    merged = m.AV2FlowAccumulator.from_state(a.state()).merge(b)
    ra, rb = whole.result(), merged.result()
    assert ra.keys() == rb.keys()
    for k in ra:
        if k == "num_sweeps":
            assert rb[k] == 2
        else:
            np.testing.assert_allclose(rb[k], ra[k], rtol=1e-12, err_msg=k)
    # The mask drops points before anything is summed.
    masked = m.AV2FlowAccumulator()
    keep = label != SIGN
    assert masked.update(true, pred, label, keep) == 56
    assert masked.result()["num_points"] == 56


def test_bad_input_names_the_argument():
    acc = m.AV2FlowAccumulator()
    z = np.zeros((2, 3))
    with pytest.raises(ValueError, match=r"flow_pred_m: shape \(3, 3\)"):
        acc.update(z, np.zeros((3, 3)), np.array([0, 0]))
    with pytest.raises(ValueError, match="label_idx: 31 at .*row 1"):
        acc.update(z, z, np.array([0, 31]))
    with pytest.raises(ValueError, match="flow_true_m: non-finite value at row 1"):
        acc.update(np.array([[0, 0, 0], [np.inf, 0, 0]]), z, np.array([0, 0]))
    with pytest.raises(ValueError, match="mask: .* expected bool"):
        acc.update(z, z, np.array([0, 0]), np.array([1, 0]))
    with pytest.raises(ValueError, match="state\\['bucket_sums'\\]"):
        m.AV2FlowAccumulator.from_state({"bucket_sums": np.zeros((3, 3)), "motion_sums": np.zeros((31, 2, 2)),
                                         "num_sweeps": 0})
    assert acc.num_sweeps == 0 and acc.bucket_sums.sum() == 0  # nothing half-added


def test_format_challenge_table():
    acc = m.AV2FlowAccumulator()
    acc.update(*_hand_case())
    r = acc.result()
    text = m.format_challenge_table(r, title="hand case")
    lines = text.splitlines()
    assert lines[0] == "hand case" and "metres per frame" in lines[1] and "57 points of 1 sweeps" in lines[1]
    car = next(line for line in lines if line.startswith("CAR"))
    assert car.split() == ["CAR", "0.0100", f"{r['bucketed/CAR/dynamic_norm_epe']:.4f}", "1", "50"]
    other = next(line for line in lines if line.startswith("OTHER_VEHICLES"))
    assert other.split() == ["OTHER_VEHICLES", "-", "-", "0", "0"]
    mean = next(line for line in lines if line.startswith("mean (leaderboard)"))
    assert mean.split()[-2:] == ["0.0060", f"{r['bucketed/mean_dynamic_norm_epe']:.4f}"]


# --- the real sample log ---------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def sample():
    """Sweep 0 of the sample log: points (sweep-0 ego frame), Argoverse's flow without ego motion (m over the pair,
    sweep-0 frame), label indices, ground and dynamic columns."""
    import pyarrow.feather as feather
    from ff3d_tf.data.av2 import argoverse2
    flow_m, points = argoverse2.argoverse_flow_in_paper_convention(AV2_LOG)
    t = feather.read_table(os.path.join(AV2_LOG, "flow_labels.feather"))
    return {"points": points, "flow_m": flow_m, "label": t.column("classes").to_numpy().astype(np.int64),
            "ground": t.column("is_ground_0").to_numpy(zero_copy_only=False),
            "dynamic": t.column("dynamic").to_numpy(zero_copy_only=False)}


def test_sample_dynamic_column_is_the_threshold(sample):
    np.testing.assert_array_equal(m.is_dynamic(sample["flow_m"]), sample["dynamic"])


def test_sample_ground_truth_as_prediction_is_zero(sample):
    acc = m.AV2FlowAccumulator()
    mask = m.eval_mask(sample["points"], sample["ground"])
    assert acc.update(sample["flow_m"], sample["flow_m"], sample["label"], mask) == 74289
    r = acc.result()
    for k in ("fg_dynamic", "fg_static", "bg_static", "mean"):
        assert r[f"three_way/{k}_epe_m"] == 0.0
    for meta in ("BACKGROUND", "CAR", "PEDESTRIAN", "WHEELED_VRU"):
        assert r[f"bucketed/{meta}/static_epe_m"] == 0.0
    assert r["bucketed/CAR/dynamic_norm_epe"] == 0.0 and r["bucketed/PEDESTRIAN/dynamic_norm_epe"] == 0.0
    assert np.isnan(r["bucketed/OTHER_VEHICLES/static_epe_m"])  # no truck points inside the mask
    assert r["bucketed/mean_static_epe_m"] == 0.0 and r["bucketed/mean_dynamic_norm_epe"] == 0.0


def _reference(points, ground, label, true, pred):
    """Straight-line reference of the community evaluator's arithmetic, one sweep: select points, then per meta-class
    and speed bucket the mean EPE and mean speed with boolean masks; meta-classes as lists of category names."""
    names = ["NONE", "ANIMAL", "ARTICULATED_BUS", "BICYCLE", "BICYCLIST", "BOLLARD", "BOX_TRUCK", "BUS",
             "CONSTRUCTION_BARREL", "CONSTRUCTION_CONE", "DOG", "LARGE_VEHICLE", "MESSAGE_BOARD_TRAILER",
             "MOBILE_PEDESTRIAN_CROSSING_SIGN", "MOTORCYCLE", "MOTORCYCLIST", "OFFICIAL_SIGNALER", "PEDESTRIAN",
             "RAILED_VEHICLE", "REGULAR_VEHICLE", "SCHOOL_BUS", "SIGN", "STOP_SIGN", "STROLLER",
             "TRAFFIC_LIGHT_TRAILER", "TRUCK", "TRUCK_CAB", "VEHICULAR_TRAILER", "WHEELCHAIR", "WHEELED_DEVICE",
             "WHEELED_RIDER"]
    meta = {"BACKGROUND": ["NONE"], "CAR": ["REGULAR_VEHICLE"],
            "OTHER_VEHICLES": ["BOX_TRUCK", "LARGE_VEHICLE", "RAILED_VEHICLE", "TRUCK", "TRUCK_CAB",
                               "VEHICULAR_TRAILER", "ARTICULATED_BUS", "BUS", "SCHOOL_BUS"],
            "PEDESTRIAN": ["PEDESTRIAN", "STROLLER", "WHEELCHAIR", "OFFICIAL_SIGNALER"],
            "WHEELED_VRU": ["BICYCLE", "BICYCLIST", "MOTORCYCLE", "MOTORCYCLIST", "WHEELED_DEVICE", "WHEELED_RIDER"]}
    sel = (~ground) & (np.abs(points[:, 0]) < 35) & (np.abs(points[:, 1]) < 35)
    cat = np.array(names)[label[sel]]
    speed = np.sqrt((true[sel] ** 2).sum(1))
    epe = np.sqrt(((pred[sel] - true[sel]) ** 2).sum(1))
    lows = [0.04 * k for k in range(51)]
    highs = lows[1:] + [np.inf]
    out = {}
    for name, cats in meta.items():
        in_cls = np.isin(cat, cats)
        static, ratios = np.nan, []
        for k, (lo, hi) in enumerate(zip(lows, highs)):
            b = in_cls & (speed >= lo) & (speed < hi)
            if not b.any():
                continue
            if k == 0:
                static = epe[b].mean()
            else:
                ratios.append(epe[b].mean() / speed[b].mean())
        out[name] = (static, np.mean(ratios) if ratios else np.nan)
    fg = np.isin(cat, sum((meta[k] for k in ("CAR", "OTHER_VEHICLES", "PEDESTRIAN", "WHEELED_VRU")), []))
    bg = cat == "NONE"
    out["three_way"] = (epe[fg & (speed >= 0.05)].mean(), epe[fg & (speed < 0.05)].mean(),
                        epe[bg & (speed < 0.05)].mean())
    return out


def test_sample_zero_flow_matches_the_reference(sample):
    zero = np.zeros_like(sample["flow_m"])
    acc = m.AV2FlowAccumulator()
    acc.update(sample["flow_m"], zero, sample["label"], m.eval_mask(sample["points"], sample["ground"]))
    r = acc.result()
    ref = _reference(sample["points"], sample["ground"], sample["label"], sample["flow_m"], zero)
    for meta in m.META_CLASSES:
        np.testing.assert_allclose(r[f"bucketed/{meta}/static_epe_m"], ref[meta][0], rtol=1e-9, err_msg=meta)
        np.testing.assert_allclose(r[f"bucketed/{meta}/dynamic_norm_epe"], ref[meta][1], rtol=1e-9, err_msg=meta)
    np.testing.assert_allclose([r["three_way/fg_dynamic_epe_m"], r["three_way/fg_static_epe_m"],
                                r["three_way/bg_static_epe_m"]], ref["three_way"], rtol=1e-9)
    np.testing.assert_allclose(r["bucketed/mean_static_epe_m"], np.nanmean([v[0] for k, v in ref.items()
                                                                            if k != "three_way"]), rtol=1e-9)
    # Zero flow: the EPE is the speed itself, so every non-empty dynamic bucket's ratio is 1 and so is its mean.
    assert r["bucketed/CAR/dynamic_norm_epe"] == pytest.approx(1.0, abs=1e-12)
    assert r["bucketed/PEDESTRIAN/dynamic_norm_epe"] == pytest.approx(1.0, abs=1e-12)
    assert r["bucketed/mean_dynamic_norm_epe"] == pytest.approx(1.0, abs=1e-12)
    # Worth stating the sample's numbers (m per frame): moving cars and pedestrians go ~0.67 m per frame.
    assert 0.5 < r["three_way/fg_dynamic_epe_m"] < 0.9 and r["three_way/bg_static_epe_m"] < 0.002


def test_sample_noisy_prediction_matches_the_reference(sample):
    rng = np.random.default_rng(3)
    pred = sample["flow_m"] + rng.normal(0, 0.05, sample["flow_m"].shape)
    acc = m.AV2FlowAccumulator()
    acc.update(sample["flow_m"], pred, sample["label"], m.eval_mask(sample["points"], sample["ground"]))
    r = acc.result()
    ref = _reference(sample["points"], sample["ground"], sample["label"], sample["flow_m"], pred)
    for meta in m.META_CLASSES:
        np.testing.assert_allclose([r[f"bucketed/{meta}/static_epe_m"], r[f"bucketed/{meta}/dynamic_norm_epe"]],
                                   ref[meta], rtol=1e-9, err_msg=meta)
    np.testing.assert_allclose(r["three_way/mean_epe_m"], np.mean(ref["three_way"]), rtol=1e-9)
