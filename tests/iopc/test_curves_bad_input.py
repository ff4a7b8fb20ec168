"""IOPC files whose records a sweep would never write; queries as tensors of any floating dtype."""

import json
import re

import numpy as np
import pytest
import torch

from camhealth.iopc import IOPC
from tests.iopc.test_curves import _records


@pytest.fixture(scope="module")
def iopc():
    return IOPC.from_records(_records(), name="AP test")


@pytest.mark.parametrize("k, field, value, match", [
    (0, "length_px", "7", r"record 0: length_px = '7' is not allowed: a finite number >= 0 px"),
    (1, "marked", 1, r"record 1: marked = 1 is not allowed: true or false"),
    (2, "marked", "false", r"record 2: marked = 'false' is not allowed: true or false"),
    (3, "ap", "x", r"record 3: ap = 'x' is not allowed: a number in \[0, 1\]"),
    (4, "noise_level_dn", -5.0, r"record 4: noise_level_dn = -5 is out of the allowed range"),
])
@pytest.mark.parametrize("suffix", [".json", ".npz"])
def test_load_checks_the_records_as_from_records_does(iopc, tmp_path, k, field, value, match, suffix):
    """A file with records[0].length_px = "7" and records[1].marked = 1 loaded, and the figure title counted the
    record with marked = 1 as marked."""
    d = json.loads(json.dumps(iopc.to_dict()))
    d["records"][k][field] = value
    path = tmp_path / f"edited{suffix}"
    if suffix == ".json":
        path.write_text(json.dumps(d))
    else:
        np.savez(path, sigma_bins_dn=iopc.sigma_bins, mtf_bins=iopc.mtf_bins, ap_2d=iopc.ap_2d, count_2d=iopc.count_2d,
                 ap_sigma=iopc.ap_sigma, count_sigma=iopc.count_sigma, ap_mtf=iopc.ap_mtf, count_mtf=iopc.count_mtf,
                 blur_length_px=iopc.blur_length_px, blur_mtf=iopc.blur_mtf,
                 meta_json=np.array(json.dumps({key: d[key] for key in ("format", "version", "name", "records",
                                                                         "provenance")})))
    with pytest.raises(ValueError, match=re.escape(f"{path}: not a camhealth IOPC file (") + match):
        IOPC.load(path)
    with pytest.raises(ValueError, match=match):
        IOPC.from_dict(d)


@pytest.mark.parametrize("field", ["ap", "length_px", "noise_level_dn"])
def test_from_dict_needs_the_fields_every_record_has(iopc, field):
    d = json.loads(json.dumps(iopc.to_dict()))
    del d["records"][2][field]
    with pytest.raises(ValueError, match=rf"record 2 is missing '{field}'"):
        IOPC.from_dict(d)


@pytest.mark.parametrize("query", ["interpolate", "length_from_mtf", "mtf_from_length"])
def test_queries_accept_bfloat16_tensors(iopc, query):
    """IOPC.interpolate(torch.tensor(…, dtype=torch.bfloat16)) was refused: "Got unsupported ScalarType BFloat16",
    although fp16 tensors were read."""
    args = {"interpolate": (torch.tensor([5.0, 2.5]), torch.tensor([0.75, 1.0])),
            "length_from_mtf": (torch.tensor([0.75, 1.0]),), "mtf_from_length": (torch.tensor([5.0, 2.5]),)}[query]
    got = getattr(iopc, query)(*(a.bfloat16() for a in args))
    np.testing.assert_allclose(got, getattr(iopc, query)(*(a.bfloat16().double().numpy() for a in args)))
