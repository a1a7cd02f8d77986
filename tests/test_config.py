"""Configuration: defaults, the shipped default file, and refusal of bad values with the key named."""

from __future__ import annotations

import re

import pytest

from condtrack_cli.config import default_yaml, load_config
from condtrack_cli.errors import CondtrackError, CondtrackWarning

from conftest import REPO


def test_default_file_is_the_code_defaults():
    assert (REPO / "configs" / "default.yaml").read_text() == default_yaml()
    assert load_config(REPO / "configs" / "default.yaml") == load_config(None)


def test_every_key_of_the_default_file_has_a_comment():
    for line in default_yaml().splitlines():
        if ":" in line and not line.lstrip().startswith("#"):
            assert "  # " in line, line


def test_override_and_method():
    config = load_config(None, ["motion.patch_size=6"], method="clf")
    assert config.stage("motion").settings.patch_size == 6
    assert config.to_dict()["motion"]["patch_size"] == 6
    assert load_config(None, ["filter.stk.win_size=15"], method="stk").filters["stk"].win_size == 15


@pytest.mark.parametrize(
    "overrides, key, hint",
    [
        (["motion.levelz=3"], "motion.levelz", "valid keys"),
        (["motion.patch_size=0"], "motion.patch_size", "greater than or equal to 4"),
        (["motion.patch_size=three"], "motion.patch_size", "integer"),
        (["motion.model=projective"], "motion.model", "'translation', 'affine' or 'quadratic'"),
        (["filter.stk.win_size=2"], "filter.stk.win_size", "greater than or equal to 3"),
        (["filter.kalman.x=1"], "filter.kalman", "valid keys"),
        (["tracker.x=1"], "tracker", "valid sections"),
        (["motion.name=nope"], "motion.name", "valid: dis, regression, robust"),
    ],
)
def test_bad_values_are_refused_naming_the_key(overrides, key, hint):
    with pytest.raises(CondtrackError) as error:
        load_config(None, overrides)
    assert f"'{key}'" in str(error.value)
    assert hint in str(error.value)


def test_unknown_method_lists_the_valid_ones():
    with pytest.raises(CondtrackError, match="filter.method.*valid: .*stk"):
        load_config(None, method="kalman")


def test_bad_files(tmp_path):
    broken = tmp_path / "broken.yaml"
    broken.write_text("motion: [levels: 3\n")
    with pytest.raises(CondtrackError, match="broken.yaml.*not valid YAML"):
        load_config(broken)
    listing = tmp_path / "list.yaml"
    listing.write_text("- 1\n- 2\n")
    with pytest.raises(CondtrackError, match="mapping of sections"):
        load_config(listing)
    with pytest.raises(CondtrackError, match="cannot read config file"):
        load_config(tmp_path / "missing.yaml")


def test_set_needs_key_and_value():
    with pytest.raises(CondtrackError, match="section.key=value"):
        load_config(None, ["motion.levels"])


@pytest.mark.parametrize("key", ["detect.max_points", "filter.stk.max_iterations"])
def test_values_opencv_cannot_take_are_refused_naming_the_key(key):
    """detect.max_points and filter.stk.max_iterations of 2^31 or more ended in OpenCV's argument-parsing traceback;
    now refused before any work, naming the key (detect.min_distance=3e9, a segmentation fault, falls under the
    float settings' bound below)."""
    with pytest.raises(CondtrackError, match=rf"config key '{key}': Input should be less than or equal to 2147483647"):
        load_config(overrides=[f"{key}={2**31}"], method="stk")
    load_config(overrides=[f"{key}={2**31 - 1}"], method="stk")


def test_an_option_setting_a_key_under_a_value_that_is_not_a_section_names_that_option(tmp_path):
    """A config file's 'filter: 3' with -m stk (or --smooth) said "--set filter.method: 'filter' is not a section",
    naming a --set never typed; now the option that sets the key, and the key's value."""
    (tmp_path / "c.yaml").write_text("filter: 3\n")
    with pytest.raises(CondtrackError, match=r"^-m stk: config key 'filter' is 3, not a section$"):
        load_config(tmp_path / "c.yaml", method="stk")
    with pytest.raises(CondtrackError, match=r"^--smooth: config key 'filter' is 3, not a section$"):
        load_config(tmp_path / "c.yaml", options={"--smooth": "filter.smooth=true"})
    with pytest.raises(CondtrackError, match=r"^--set filter.x=2: config key 'filter.x' is 2, not a section$"):
        load_config(overrides=["filter.x=2", "filter.x.y=1"])


@pytest.mark.parametrize("method, options", [("clf", {}), (None, {"--smooth": "filter.smooth=true"})])
def test_a_set_that_makes_a_section_a_value_is_named_not_the_option_after_it(method, options):
    """'--set filter=3 -m clf' said "-m clf: config key 'filter' is 3, not a section", blaming the -m (or --smooth)."""
    with pytest.raises(CondtrackError, match=r"^--set filter=3: config key 'filter' is 3, not a section$"):
        load_config(overrides=["filter=3"], method=method, options=options)


@pytest.mark.parametrize("key", ["measure.noise_sigma", "motion.q_floor", "filter.clf.drift_check", "detect.min_distance"])
def test_a_float_setting_beyond_1e9_is_refused_naming_the_key(key):
    """--set filter.clf.initial_std=1e200 (or measure.noise_sigma=1e300, ...) ended in an OverflowError traceback or
    in inf/nan covariances with RuntimeWarnings; every float setting is now at most 1e9 in magnitude."""
    with pytest.raises(CondtrackError, match=rf"config key '{key}': Value error, must be at most 1e\+09 in magnitude"):
        load_config(overrides=[f"{key}=1e200"], method="clf")
    load_config(overrides=[f"{key}=1e9"], method="clf")
    assert load_config(overrides=["output.max_std=1e16"]).output.max_std == 1e16  # a threshold only: not bounded


def test_the_initial_std_is_at_most_a_thousand_pixels():
    """filter.cnlf.initial_std=1e6 spread the particles so far that the CNLF's weights underflowed (an IndexError
    traceback); a thousand pixels, larger than any frame's reach a query needs, is the bound."""
    with pytest.raises(CondtrackError, match=r"config key 'filter.cnlf.initial_std': Input should be less than or equal to 1000"):
        load_config(overrides=["filter.cnlf.initial_std=1001"], method="cnlf")
    load_config(overrides=["filter.cnlf.initial_std=1000"], method="cnlf")


@pytest.mark.parametrize("text, key, shown", [
    ("filter: []\n", "filter", "[]"), ("output: 0\n", "output", "0"), ("output: false\n", "output", "False"),
    ("filter:\n  stk: ''\n", "filter.stk", "''"), ("filter:\n  clf: 0\n", "filter.clf", "0"),
])
def test_a_section_given_as_a_false_value_is_refused_like_any_other_non_mapping(tmp_path, text, key, shown):
    """'filter: []', 'output: 0' or 'output: false' (a false value, read as "no section") ran on the defaults with no
    word, while 'output: 5' was refused; every section that is not a mapping is now refused, naming its key. An empty
    section (the key alone, YAML null) is still no setting."""
    (tmp_path / "c.yaml").write_text(text)
    with pytest.raises(CondtrackError, match=rf"^config key '{key}': expected a mapping.*, got {re.escape(shown)}$"):
        load_config(tmp_path / "c.yaml")
    (tmp_path / "c.yaml").write_text("filter:\n  stk:\noutput:\nmotion:\n")
    assert load_config(tmp_path / "c.yaml") == load_config(None)


@pytest.mark.parametrize("sigma", ["0.3", "1e-200"])
def test_a_weight_sigma_under_half_a_pixel_is_refused(sigma):
    """measure.weight_sigma=1e-200 ran with numpy's 'overflow encountered in square' warning, and every sigma well
    under a pixel weighed the centre pixel alone (zero_mean: every cost 0, 3 % of the occlusion sample's rows
    visible); the bound is 0.5 px."""
    with pytest.raises(CondtrackError, match=rf"^config key 'measure.weight_sigma': Input should be greater than or "
                                             rf"equal to 0.5 \(got {sigma}\)$"):
        load_config(overrides=[f"measure.weight_sigma={sigma}"])
    assert load_config(overrides=["measure.weight_sigma=0.5"]).stages["measure"].settings.weight_sigma == 0.5


def test_mdr_runs_no_measure_stage_so_its_keys_are_warned_and_its_window_need_not_fit():
    """-m mdr (the motion alone) took --set measure.* without a word though nothing changed (the tracks the same bit
    for bit), and refused a frame smaller than measure.template, a window it never reads."""
    with pytest.warns(CondtrackWarning, match=r"^--set measure.template=63 has no effect: method 'mdr' runs no "
                                              r"measure stage$"):
        config = load_config(overrides=["measure.template=63"], method="mdr")
    config.check_fits_frame(40, 40, detecting=False)
    with pytest.raises(CondtrackError, match="config key 'measure.template': a window of 63 px does not fit"):
        load_config(overrides=["measure.template=63"], method="clf").check_fits_frame(40, 40, detecting=False)
