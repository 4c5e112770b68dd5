"""The two seed types Debian does not package, served with the seed's type names and md5 sums so that a client
written for them (openai_ros, a GazeboConnection) talks to the sim node unchanged: ``std_srvs/Empty`` (the
``/gazebo/*`` services) and ``openai_ros/RLExperimentInfo`` (``/openai/reward``), generated with genpy."""
from __future__ import annotations

from jaxrobo_ros.system import rospy

rospy()  # puts the system's genpy on the path where needed
import genpy  # noqa: E402
from genpy.dynamic import generate_dynamic  # noqa: E402

#: md5 of an empty message definition: std_srvs/Empty's request, response and service.
EMPTY_MD5 = "d41d8cd98f00b204e9800998ecf8427e"

RLExperimentInfo = generate_dynamic("openai_ros/RLExperimentInfo",
                                    "int32 episode_number\nfloat32 episode_reward\n")["openai_ros/RLExperimentInfo"]


class EmptyRequest(genpy.Message):
    _md5sum, _type, _has_header, _full_text = EMPTY_MD5, "std_srvs/EmptyRequest", False, ""
    __slots__: list = []
    _slot_types: list = []

    def _get_types(self):
        return self._slot_types

    def serialize(self, buff):
        pass

    def deserialize(self, str):  # noqa: A002 - genpy's signature
        return self


class EmptyResponse(EmptyRequest):
    _type = "std_srvs/EmptyResponse"
    __slots__: list = []


class Empty:
    """``std_srvs/Empty``: no request fields, no response fields."""

    _type, _md5sum = "std_srvs/Empty", EMPTY_MD5
    _request_class, _response_class = EmptyRequest, EmptyResponse
