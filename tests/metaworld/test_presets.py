"""The presets resolve to the policy's action layout (issue 55, item 4), and method strings take numbers in ASCII
digits only, with one wording per option's range (item 5). No model is loaded."""

from __future__ import annotations

import re

import pytest

from hf_specvla import ActionLayout, ActionTokenizer, make_acceptance_rule
from hf_specvla.metaworld.comparison import PRESETS, DecodingMethod, parse_methods, resolve_preset
from hf_specvla.metaworld.comparison.methods import CompareConfig
from hf_specvla.policies.devices import Placement

FAST = {
    4: "prior+jacobi:r=4/4/4/0,gate=0.5,confirm=1:compile",  # x y z gripper
    7: "prior+jacobi:r=4/4/4/0/0/0/0,gate=0.5,confirm=1:compile",  # OpenVLA: x y z roll pitch yaw gripper
    8: "prior+jacobi:r=4/4/4/0/0/0/0/0,gate=0.5,confirm=1:compile",  # x y z, a quaternion, gripper
}


@pytest.mark.parametrize("action_dim", sorted(FAST))
def test_fast_relaxes_the_position_only_on_every_known_layout(action_dim):
    for head in (False, True):
        method = DecodingMethod.parse("fast", draft_head_given=head, action_dim=action_dim)
        assert method.name == FAST[action_dim] == resolve_preset("fast", head, action_dim)
        assert DecodingMethod.parse(method.name, action_dim=action_dim) == method  # the name parses back
    # the engine builds its rule for actions of that size (the old table r=4/4/4/0 was refused on 7 dimensions)
    layout = ActionLayout(ActionTokenizer(512), action_dim)
    rule = make_acceptance_rule(action_layout=layout, **method.rule_kwargs(action_dim))
    assert "4, 4, 4, 0" in repr(rule)


def test_fast_is_defined_by_what_it_relaxes():
    fast = PRESETS["fast"]
    assert (fast.position_tolerance, fast.rotation_tolerance, fast.gripper_tolerance) == (4, 0, 0)
    assert fast.confidence_gate == 0.5 and fast.compiled and not fast.lossless


def test_exact_fits_any_layout():
    for action_dim in (1, 4, 6, 7, 8, 12):
        method = DecodingMethod.parse("exact", action_dim=action_dim)
        assert method.name == "prior+jacobi:compile" and method.lossless


@pytest.mark.parametrize("action_dim", [1, 3, 6, 9])
def test_fast_on_an_unknown_layout_names_the_rule_to_spell_out(action_dim):
    with pytest.raises(ValueError) as error:
        DecodingMethod.parse("fast", action_dim=action_dim)
    message = str(error.value)
    assert "preset 'fast'" in message and f"{action_dim}-dimensional actions have no known layout" in message
    assert "7: x y z roll pitch yaw gripper" in message
    spelled = message.rsplit("e.g. ", 1)[1]
    assert DecodingMethod.parse(spelled, action_dim=action_dim).widest_tolerance == 4  # the hint parses


@pytest.mark.parametrize("action_dim", [0, -4, 4.0, True, "4"])
def test_an_action_dim_that_is_not_a_positive_int_is_refused_naming_it(action_dim):
    # issue 64: action_dim=0 failed inside the preset's hint with "max() arg is an empty sequence"
    expected = rf"action_dim must be a positive int .*got {re.escape(repr(action_dim))}$"
    for text in ("fast", "exact", "prior:r=4"):
        with pytest.raises(ValueError, match=expected):
            DecodingMethod.parse(text, action_dim=action_dim)
    with pytest.raises(ValueError, match=expected):
        PRESETS["fast"].resolve(action_dim=action_dim)
    with pytest.raises(ValueError, match=expected):
        resolve_preset("fast", False, action_dim)
    with pytest.raises(ValueError, match=expected):
        DecodingMethod.parse("prior:r=4,rl=2").generate_kwargs(None, action_dim=action_dim)


def test_without_an_action_dim_presets_resolve_for_this_projects_policies():
    assert DecodingMethod.parse("fast").name == FAST[4]
    assert [m.name for m in parse_methods(["fast"], action_dim=7)] == ["greedy", FAST[7]]


def test_compare_config_resolves_presets_to_the_policys_layout():
    config = CompareConfig("reach", 1, ["exact", "fast"], action_dim=7)
    assert config.methods == ["greedy", "prior+jacobi:compile", FAST[7]]
    with pytest.raises(ValueError, match="CompareConfig.action_dim must be >= 1, got 0"):
        CompareConfig("reach", 1, ["fast"], action_dim=0)
    with pytest.raises(ValueError, match="no known layout"):
        CompareConfig("reach", 1, ["fast"], action_dim=5)


def test_a_per_dimension_r_must_fit_the_action():
    with pytest.raises(ValueError) as error:
        DecodingMethod.parse("prior:r=4/4/4", action_dim=4)
    assert str(error.value) == (
        "decoding method 'prior:r=4/4/4': r=4/4/4 has 3 values, but the policy's actions have 4 dimensions "
        "(x y z gripper): give one value for all of them, or one per dimension (4)"
    )
    with pytest.raises(ValueError, match="rl=6/6 has 2 values"):
        DecodingMethod.parse("prior:r=2,rl=6/6", action_dim=7)
    assert DecodingMethod.parse("prior:r=4/4/4/0/0/0/0", action_dim=7).bin_tolerance == (4, 4, 4, 0, 0, 0, 0)
    assert DecodingMethod.parse("prior:r=4/4/4").bin_tolerance == (4, 4, 4)  # no action_dim: the engine checks later


@pytest.mark.parametrize(
    "text, message",
    [
        ("prior:r=²", "decoding method 'prior:r=²': bad option 'r=²'"),  # str.isdigit() is True, int() fails
        ("prior:r=٣", "decoding method 'prior:r=٣': bad option 'r=٣'"),  # int() would read 3
        ("prior:r=4/٣", "bad option 'r=4/٣'"),
        ("prior:r=2,rl=٣", "bad option 'rl=٣'"),
        ("prior:r=4,m=²", "bad option 'm=²'"),
        ("prior:r=4,m=١", "bad option 'm=١'"),
        ("head:k=٣", "bad option 'k=٣'"),
        ("prior:r=4,gate=٠.٥", "gate must be a probability in (0, 1] written in digits 0-9"),  # float() reads 0.5
        ("prior:r=4,gate=0.5_0", "got gate=0.5_0"),  # float() reads 0.5
        ("prior:r=4,gate=nan", "got gate=nan"),
    ],
)
def test_numbers_are_ascii_digits(text, message):
    with pytest.raises(ValueError) as error:
        DecodingMethod.parse(text)
    assert message in str(error.value)


@pytest.mark.parametrize("value", ["0", "-1", "-7"])
def test_a_chain_length_below_one_has_one_message(value):
    with pytest.raises(ValueError) as error:
        DecodingMethod.parse(f"head:k={value}")
    assert str(error.value) == (
        f"decoding method 'head:k={value}': k must be an integer >= 1 (draft-head chain length (head only)), "
        f"got k={value}"
    )


def test_ascii_numbers_still_parse():
    method = DecodingMethod.parse("prior+head:r=4/4/4/0,rl=8,m=1,gate=.25,k=3")
    assert (method.bin_tolerance, method.later_tolerance, method.max_relaxed_per_action) == ((4, 4, 4, 0), 8, 1)
    assert (method.confidence_gate, method.num_draft_tokens) == (0.25, 3)
    assert DecodingMethod.parse("prior:r=4,gate=1").confidence_gate == 1.0


def test_the_compare_command_resolves_presets_to_the_policys_layout(tmp_path, monkeypatch):
    """``hf-specvla compare`` reads the policy's action_dim from its config (before loading it) and resolves ``fast``
    for it: a 7-dimensional (OpenVLA-shaped) policy gets the 7-dimensional table."""
    from types import SimpleNamespace

    from hf_specvla.cli import compare, main
    from hf_specvla.metaworld import comparison

    seen = {}

    def record(policy, config, *args, **kwargs):
        seen["methods"] = config.methods
        raise ValueError("stop here")  # a usage error: nothing runs

    monkeypatch.setattr(compare, "read_policy_config", lambda *a, **k: SimpleNamespace(action_dim=7))
    monkeypatch.setattr(compare, "load_policy", lambda *a, **k: None)
    monkeypatch.setattr(Placement, "place_policy", lambda *a, **k: None)  # no policy loaded: nothing to place
    monkeypatch.setattr(comparison, "run_comparison", record)
    with pytest.raises(SystemExit):
        main(["compare", "--policy", "unused", "--tasks", "reach", "--methods", "fast", "--threads", "1",
              "--output-dir", str(tmp_path / "out")])  # fmt: skip
    assert seen["methods"] == ["greedy", FAST[7]]


# ----------------------------------------------------------------------------- rules that scale with the motion
def test_motion_rules_parse_name_and_build():
    """rho, dev and confirm parse, name themselves canonically (the name parses back) and become the engine's rule."""
    from hf_specvla import ActionUnits, StrictTailConfirmed

    text = "prior+jacobi:rho=0.25/0.25/0.25/0,dev=.08/.08/.08/0,confirm=1:compile"
    method = DecodingMethod.parse(text, action_dim=4)
    assert method.name == "prior+jacobi:rho=0.25/0.25/0.25/0,dev=0.08/0.08/0.08/0,confirm=1:compile"
    assert DecodingMethod.parse(method.name, action_dim=4) == method and not method.lossless
    kwargs = method.rule_kwargs(4)
    assert kwargs == {"bin_tolerance": 0, "motion_scale": [0.25, 0.25, 0.25, 0.0],
                      "max_deviation": [0.08, 0.08, 0.08, 0.0], "confirm_strict_tail": True}  # fmt: skip
    layout = ActionLayout(ActionTokenizer(512), 4, ActionUnits((127,) * 4, (2 / 255,) * 4))
    rule = make_acceptance_rule(action_layout=layout, **kwargs)
    assert isinstance(rule, StrictTailConfirmed) and rule.strict_tail == (3, 3, 3, -1)
    assert int(rule.rule.tolerance_by_bin.max()) == 10  # 0.08 units / (2/255 per bin)
    assert DecodingMethod.parse("prior:r=4/4/4/0,gate=0.5,confirm=1").confirm_tail


def test_rho0_is_lossless_and_restricting_options_need_a_relaxation():
    assert DecodingMethod.parse("prior+jacobi:rho=0").lossless
    assert DecodingMethod.parse("prior+jacobi:rho=0").rule_kwargs(4) == {}
    for text in ("prior:dev=0.1", "prior:confirm=1", "prior:rho=0,dev=0.1"):
        with pytest.raises(ValueError, match="only restrict relaxed acceptance; give r .* or rho > 0 too"):
            DecodingMethod.parse(text)


@pytest.mark.parametrize(
    "text, message",
    [("greedy:rho=0.1", "greedy takes no r, rl, rho, dev, m, gate, confirm or k"),
     ("prior:rho=-0.1", "bad option 'rho=-0.1'"),
     ("prior:rho=0.1/x", "numbers >= 0 in digits 0-9"),
     ("prior:rho=0.1/0.1", "rho=0.1/0.1 has 2 values, but the policy's actions have 4 dimensions"),
     ("prior:r=2,dev=1/1/1", "dev=1/1/1 has 3 values"),
     ("prior:r=2,confirm=yes", "confirm is 0 or 1"),
     ("prior:r=2,confirm=1,confirm=1", "confirm given twice")],
)  # fmt: skip
def test_bad_motion_rule_options_are_named(text, message):
    with pytest.raises(ValueError) as error:
        DecodingMethod.parse(text, action_dim=4)
    assert message in str(error.value)


def test_a_server_given_a_head_measures_each_preset_with_and_without_it():
    """Offline, a preset resolves to one method, the same with a head; a server given a head measures the preset's
    head composition beside it (issue 62, item 4), in the same relaxation; lists keep their order, repeats dropped."""
    from hf_specvla.policies.decoding_methods import serving_methods

    assert [m.name for m in serving_methods("exact")] == ["prior+jacobi:compile"]
    assert [m.name for m in serving_methods("exact", draft_head_given=True)] == [
        "prior+jacobi:compile", "prior+jacobi+tree:compile"]  # fmt: skip
    assert DecodingMethod.parse("exact", draft_head_given=True).name == "prior+jacobi:compile"  # offline: unchanged
    fast = [m.name for m in serving_methods("fast", True, 7)]
    assert fast == [FAST[7], FAST[7].replace("prior+jacobi:", "prior+jacobi+tree:")]
    listed = serving_methods(["prior+jacobi:compile", "exact", "prior+tree:compile"], True)
    assert [m.name for m in listed] == ["prior+jacobi:compile", "prior+jacobi+tree:compile", "prior+tree:compile"]
    assert [m.name for m in serving_methods("greedy:compile", True)] == ["greedy:compile"]


@pytest.mark.parametrize(
    ("methods", "message"),
    [
        (["prior+jacobi", "prior+jacobi:compile"], "mix compiled and eager"),
        (["greedy:compile", "exact"], "greedy is the baseline"),
        (["prior+bogus"], "unknown decoding method"),
        ([], "a list of them"),
    ],
)
def test_a_server_s_methods_that_cannot_be_measured_together_are_refused(methods, message):
    from hf_specvla.policies.decoding_methods import serving_methods

    with pytest.raises(ValueError, match=message):
        serving_methods(methods)
