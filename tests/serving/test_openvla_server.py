"""An OpenVLA checkpoint served through ``/act`` (a real HTTP server on 127.0.0.1, started by each test and stopped
after): OpenVLA's own client (json_numpy, its field names, its double-encoded form) gets, at K = 1, 4 and 8 robots
in batches, every action the one-robot greedy ``predict_action`` gives; ``unnorm_key`` from the request, the server's
default or a 422 naming the valid keys; images of any size."""

from __future__ import annotations

import json
import threading
import urllib.error
import urllib.request

import numpy as np
import pytest

from hf_specvla.policies import OpenVLAPolicy
from hf_specvla.serving import PolicyClient, PolicyService, ServeConfig
from hf_specvla.serving.protocol import dumps
from hf_specvla.serving.server import PolicyServer
from tests.openvla.test_openvla import NORM_STATS, needs_hub_files
from tests.openvla.tiny_checkpoint import write_tiny_checkpoint

pytestmark = needs_hub_files

#: eager decoding (no compile): what is served, not how fast, is under test
METHOD = "prior+jacobi"
INSTRUCTIONS = ("pick up the red block", "open the top drawer of the cabinet", "push the button", "close the door")
KEYS = ("tiny_dataset", "other_dataset")


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return write_tiny_checkpoint(tmp_path_factory.mktemp("tiny-openvla"))


@pytest.fixture(scope="module")
def policy(checkpoint) -> OpenVLAPolicy:
    return OpenVLAPolicy.from_pretrained(checkpoint, unnorm_key="tiny_dataset")


def _service(policy, **settings) -> PolicyService:
    config = dict(method=METHOD, buckets=(1, 2, 4, 8), calibration_calls=0, max_wait_ms=30.0)
    return PolicyService(policy, ServeConfig(**{**config, **settings}))


def _observation(seed: int) -> dict:
    rng = np.random.default_rng(seed)
    side = (224, 256, 180)[seed % 3]  # a robot's camera image, any size: the processor resizes it
    return {
        "image": rng.integers(0, 256, (side, side, 3), dtype=np.uint8),
        "instruction": INSTRUCTIONS[seed % len(INSTRUCTIONS)],
        "unnorm_key": KEYS[seed % 2],
    }


def _greedy(policy, observation: dict) -> np.ndarray:
    """The port's own one-robot greedy call: what every served action must equal."""
    return policy.model.predict_action(
        image=observation["image"],
        instruction=observation["instruction"],
        processor=policy.processor,
        unnorm_key=observation["unnorm_key"],
        do_sample=False,
    )


def _post(url: str, payload) -> tuple[int, dict]:
    request = urllib.request.Request(url + "/act", dumps(payload), {"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(request, timeout=120) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as error:
        return error.code, json.loads(error.read() or b"null")


def test_openvlas_own_client_gets_the_one_robot_action(policy):
    """deploy.py's client, verbatim: ``json_numpy.patch()`` then ``requests.post(url, json=...)``, and its
    double-encoded form."""
    requests = pytest.importorskip("requests")
    json_numpy = pytest.importorskip("json_numpy")
    observation = _observation(1)
    expected = _greedy(policy, observation)
    saved = json.dumps, json.loads, json.dump, json.load
    with PolicyServer(_service(policy), port=0) as server:
        json_numpy.patch()
        try:
            action = requests.post(server.url + "/act", json=observation).json()
            encoded = json.loads(requests.post(server.url + "/act", json={"encoded": json.dumps(observation)}).json())
        finally:
            json.dumps, json.loads, json.dump, json.load = saved
        info = PolicyClient(server.url).info()
    assert isinstance(action, np.ndarray) and action.dtype == np.float64 and action.shape == (7,)
    np.testing.assert_array_equal(action, expected)
    np.testing.assert_array_equal(encoded, expected)
    assert info["unnorm_keys"] == sorted(KEYS) and info["unnorm_key"] == "tiny_dataset"
    assert info["image_size"] is None and info["action_dim"] == 7 and info["state_dim"] == 0


@pytest.mark.parametrize("robots", [1, 4, 8])
def test_robots_in_batches_each_get_the_one_robot_action(policy, robots):
    """K robots at once, 3 steps each (drafting from their own previous actions, kept by session): every action is
    the one-robot greedy action of that observation, whatever batches formed."""
    observations = [[_observation(10 * robot + step) for step in range(3)] for robot in range(robots)]
    expected = [[_greedy(policy, o) for o in steps] for steps in observations]
    replies: dict = {}
    with PolicyServer(_service(policy), port=0) as server:

        def robot(i: int) -> None:
            client = PolicyClient(server.url)
            for step, o in enumerate(observations[i]):
                replies[i, step] = client.act(
                    o["image"], o["instruction"], session=f"r{i}", reset=step == 0, unnorm_key=o["unnorm_key"]
                )

        threads = [threading.Thread(target=robot, args=(i,)) for i in range(robots)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
    assert len(replies) == 3 * robots
    for (i, step), reply in replies.items():
        np.testing.assert_array_equal(reply.action, expected[i][step], err_msg=f"robot {i} step {step}")
    if robots > 1:
        assert max(r.served.batch_size for r in replies.values()) > 1, "no batch formed: the test tests nothing"
    assert any(r.served.speculative and r.served.target_forwards < 7 for r in replies.values())


def test_unnorm_key_from_the_request_the_default_or_a_422_naming_the_keys(policy, checkpoint, tmp_path):
    observation = _observation(2)
    no_key = {k: v for k, v in observation.items() if k != "unnorm_key"}
    two = OpenVLAPolicy(policy.model, policy.processor)  # two datasets, no default: each request names one
    with PolicyServer(_service(two), port=0) as server:
        status, body = _post(server.url, no_key)
        assert status == 422 and body["field"] == "unnorm_key"
        assert "pass unnorm_key, one of ['other_dataset', 'tiny_dataset']" in body["error"]
        status, body = _post(server.url, {**observation, "unnorm_key": "bridge_orig"})
        assert status == 422 and body["field"] == "unnorm_key"
        assert "unnorm_key='bridge_orig' is not in this checkpoint's norm_stats; valid keys: " in body["error"]
        status, body = _post(server.url, observation)
        assert status == 200
    np.testing.assert_array_equal(_decode(body), _greedy(policy, observation))
    # a checkpoint of one dataset: a request without a key is un-normalised with it
    only = write_tiny_checkpoint(tmp_path / "one", norm_stats={"tiny_dataset": NORM_STATS["tiny_dataset"]})
    single = OpenVLAPolicy.from_pretrained(only)
    with PolicyServer(_service(single), port=0) as server:
        status, body = _post(server.url, no_key)
        bad_image = _post(server.url, {**no_key, "image": np.zeros((8, 8), dtype=np.uint8)})
    assert status == 200
    np.testing.assert_array_equal(_decode(body), _greedy(policy, {**observation, "unnorm_key": "tiny_dataset"}))
    assert bad_image[0] == 422 and bad_image[1]["field"] == "image" and "[H, W, 3]" in bad_image[1]["error"]


def _decode(body: dict) -> np.ndarray:
    from hf_specvla.serving.protocol import decode_array

    return decode_array(body, "action")


def test_a_policy_that_takes_any_image_size_still_refuses_what_is_not_an_image():
    from hf_specvla.serving.protocol import MAX_IMAGE_SIDE, ActRequest, RequestError

    def parse(image) -> ActRequest:
        return ActRequest.parse({"image": image, "instruction": "push", "unnorm_key": "bridge_orig"}, None, 0, False)

    request = parse(np.zeros((120, 160, 3), np.uint8))
    assert request.image.shape == (120, 160, 3) and request.unnorm_key == "bridge_orig"
    for image in (
        np.zeros((0, 5, 3), np.uint8),
        np.zeros((MAX_IMAGE_SIDE + 1, 4, 3), np.uint8),
        np.zeros((8, 8), np.uint8),
        np.zeros((8, 8, 4), np.uint8),
        np.zeros((8, 8, 3), np.float32),
    ):
        with pytest.raises(RequestError, match=r"image must be uint8 of shape \[H, W, 3\] \(sides 1\.\.4096\)"):
            parse(image)
