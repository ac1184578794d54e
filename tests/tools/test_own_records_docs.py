"""The figures docs/datasets.md quotes about your own sequences are those of benchmarks/own_records_cpu.json (made by
`python -m lab.labels.own_records_bench`) and, for the Argoverse 2 records path, benchmarks/nsfp_cpu.json,
formatted here as the page must show them (wrapped as you like). `python tests/tools/test_own_records_docs.py`
prints them."""
import json
import os

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.realpath(__file__))))
DOC = os.path.join(ROOT, "docs", "datasets.md")


def _json(name):
    with open(os.path.join(ROOT, "benchmarks", name)) as f:
        return json.load(f)


def _flat(text):
    return " ".join(text.split())


def _machine(bench) -> str:
    m = bench["machine"]
    return f"a {m['cpu_count']}-core {m['model_name']} VM (family/model {m['family_model']})"


def quotes() -> list[str]:
    bench, reference = _json("own_records_cpu.json"), _json("nsfp_cpu.json")
    sample = bench["av2_sample_as_files"]
    labels, nsfp, ground = sample["labels"], sample["nsfp"], sample["ground"]
    speed, where = bench["records_speed"], nsfp["where_the_error_lies"]
    rule = ground["height_rule_of_the_pair"]["t0"]
    bar = reference["av2_sample"]["bar_at_most"]
    return [
        f"labels {labels['same_label_share']:.1%} of the {labels['points']:,} points of its second sweep as the "
        f"Argoverse 2 path does (the same class, and flow within 1 mm/s; {labels['object_points']:,} of them in "
        "objects' boxes).",
        f"scores a three-way EPE of {nsfp['three_way_epe_m']:.3f} m by the challenge's arithmetic over its 35 m box "
        f"({nsfp['evaluated_points']:,} points; zero flow {nsfp['zero_flow_three_way_epe_m']:.3f} m; the "
        f"Argoverse 2 records path's pseudo-labels, with the map's ground, "
        f"{reference['av2_sample']['nsfp']['three_way/mean_epe_m']:.3f} m: `benchmarks/nsfp_cpu.json`), after "
        f"{nsfp['fit_steps']:,} steps and {nsfp['fit_seconds']:,.0f} s of fitting on {_machine(bench)}.",
        f"its bucketed normalized dynamic EPE, {nsfp['bucketed_dynamic_norm_epe']:.3f}, is "
        f"{'above' if nsfp['bucketed_dynamic_norm_epe'] > bar['bucketed/mean_dynamic_norm_epe'] else 'within'} that "
        f"bar's {bar['bucketed/mean_dynamic_norm_epe']:.3f}.",
        f"{nsfp['evaluated_points_without_prediction']:,} of the evaluated points have no prediction (above the "
        "fit's crop; zero flow in the challenge's arithmetic), as "
        f"{reference['av2_sample']['evaluated_points_without_pseudo_label']:,} have none in the records path. With "
        "the true flow put in on every point the fit did not predict (those, and the ground rule's), the score is "
        f"{where['truth_where_not_fitted_three_way_epe_m']:.3f} m; with it put in on the fitted points, "
        f"{where['truth_where_fitted_three_way_epe_m']:.4f} m.",
        f"calls {rule['ground_not_on_map']:,} points of the t0 cloud's crop ground that the map does not, and leaves "
        f"{rule['map_ground_not_called_ground']:,} of the map's ground in the fit.",
        f"Records of {speed['points_per_sweep']:,}-point sweeps are written at "
        f"{speed['with_boxes']['pairs_per_cpu_s']:.1f} pairs per CPU second with a box table of "
        f"{speed['boxes_per_sweep']} boxes a sweep and {speed['without_boxes']['pairs_per_cpu_s']:.1f} without "
        f"({speed['with_boxes']['bytes_per_pair'] / 1e6:.1f} MB a pair; `python -m lab.labels.own_records_bench`, "
        f"{_machine(bench)}).",
    ]


def test_quoted_figures_are_their_json():
    with open(DOC, encoding="utf-8") as f:
        text = _flat(f.read())
    missing = [q for q in quotes() if _flat(q) not in text]
    assert not missing, f"docs/datasets.md must say (wrapped as you like): {missing}"


if __name__ == "__main__":
    print("\n\n".join(quotes()))
