"""CameraMetadata.from_dict / sample(fixed=…) given a ``sensor`` key: it names a preset, not a field, and the message says
how to start from that preset."""

from __future__ import annotations

import re

import pytest

from camhealth.physics import CameraMetadata


@pytest.mark.parametrize("call", [
    lambda: CameraMetadata.from_dict({"sensor": "ICX285", "gain_db": 6.0}, base="ICX285"),
    lambda: CameraMetadata.from_dict({"sensor": "EV76C661"}),
    lambda: CameraMetadata.sample(2, fixed={"sensor": "ICX285"}),
], ids=["from_dict", "from_dict_no_base", "sample_fixed"])
def test_a_sensor_key_is_named_as_a_preset_with_how_to_use_it(call):
    """A mapping holding ``sensor: ICX285`` (as a metadata file may) only said "unknown metadata field(s) ['sensor']"."""
    with pytest.raises(ValueError, match=r"unknown metadata field\(s\) \['sensor'\]; known fields: \[.*\]; "
                                         r"sensor = '\w+' names a preset, not a field: start from it with "
                                         r"CameraMetadata\.preset\('\w+', …\) or from_dict\(…, base='\w+'\)"):
        call()


def test_the_way_the_message_names_works():
    meta = CameraMetadata.from_dict({"gain_db": 6.0}, base="ICX285")
    assert float(meta.gain_db[0]) == 6.0
    assert meta.to_dict() == CameraMetadata.preset("ICX285", gain_db=6.0).to_dict()


def test_other_unknown_keys_get_no_preset_hint():
    with pytest.raises(ValueError, match=re.escape("unknown metadata field(s) ['gain']; known fields: ")) as err:
        CameraMetadata.from_dict({"gain": 3.0}, base="ICX285")
    assert "preset" not in str(err.value)
