"""frf.json / frf.csv as untrusted input (issue 16): every bad file is one torchblur error that
names the path, never a RecursionError, UnicodeDecodeError, KeyError or csv.Error."""
import json

import numpy as np
import pytest

from torchblur.errors import InputTypeError, ParameterError, ShapeError, TorchblurError
from torchblur.sysid import frequency_response_io as fr
from torchblur.sysid.frequency_response import FrequencyResponse


@pytest.fixture
def doc():
    omega = np.array([10.0, 100.0, 1000.0])
    return FrequencyResponse(omega, 1.0 / (1.0 + 1j * omega / 300.0)).to_dict()


def _bad_json(doc):
    def with_(**kw):
        return json.dumps({**doc, **kw})

    deep = "[" * 10_000 + "]" * 10_000
    return {
        "empty": b"",
        "blank": b"  \n",
        "binary": bytes(range(256)) * 4,
        "utf16": json.dumps(doc).encode("utf-16"),
        "deep_list": deep.encode(),
        "deep_object": ('{"a":' * 10_000 + "1" + "}" * 10_000).encode(),
        "deep_in_field": with_(omega=json.loads("[" * 200 + "1" + "]" * 200)).encode(),
        "not_json": b"omega = 1, 2, 3",
        "truncated": json.dumps(doc)[:-7].encode(),
        "a_list": b"[1, 2, 3]",
        "a_string": b'"frf"',
        "no_schema": json.dumps({k: v for k, v in doc.items() if k != "schema"}).encode(),
        "missing_omega": json.dumps({k: v for k, v in doc.items() if k != "omega"}).encode(),
        "omega_string": with_(omega="fast").encode(),
        "omega_dicts": with_(omega=[{"a": 1}] * 3).encode(),
        "ragged": with_(response_real=[[1, 2], [3]]).encode(),
        "short_imag": with_(response_imag=[0.0]).encode(),
        "labels_number": with_(output_labels=7).encode(),
        "labels_dicts": with_(input_labels=[{"x": 1}]).encode(),
        "meta_list": with_(meta=[1, 2]).encode(),
        "cov_string": with_(cov="none").encode(),
        "version_true": with_(schema_version=True).encode(),
        "huge_number": json.dumps(doc).replace("10.0", "1" + "0" * 5000, 1).encode(),
    }


@pytest.mark.parametrize("case", list(_bad_json({"schema": "x"}).keys()))
def test_bad_frf_json_is_one_error_naming_the_path(case, doc, tmp_path):
    path = tmp_path / "frf.json"
    path.write_bytes(_bad_json(doc)[case])
    with pytest.raises((ParameterError, InputTypeError, ShapeError)) as info:
        FrequencyResponse.from_json(path)
    assert str(path) in str(info.value)


def test_good_frf_json_still_reads(doc, tmp_path):
    path = tmp_path / "frf.json"
    path.write_text(json.dumps(doc))
    assert FrequencyResponse.from_json(path).omega.tolist() == doc["omega"]


def test_huge_response_files_are_refused_before_reading(tmp_path, monkeypatch):
    monkeypatch.setattr(fr, "MAX_FILE_BYTES", 1000)
    for name, reader in (("frf.json", FrequencyResponse.from_json), ("frf.csv", FrequencyResponse.from_csv)):
        path = tmp_path / name
        with open(path, "wb") as fh:
            fh.truncate(1001)  # sparse: nothing is read
        with pytest.raises(ParameterError, match="larger than") as info:
            reader(path)
        assert str(path) in str(info.value)


BAD_CSV = {
    "empty": b"",
    "binary": bytes(range(256)) * 4,
    "nul": b"freq_hz,magnitude,phase_deg,magnitude_std,phase_std_deg\n1,\x002,3,4,5\n",
    "header_only": b"freq_hz,magnitude,phase_deg,magnitude_std,phase_std_deg\n",
    "words": b"freq_hz,magnitude,phase_deg,magnitude_std,phase_std_deg\n1,two,3,4,5\n",
    "columns": b"freq_hz,magnitude,phase_deg,magnitude_std,phase_std_deg\n1,2,3\n",
    "negative": b"freq_hz,magnitude,phase_deg,magnitude_std,phase_std_deg\n1,-2,3,4,5\n",
    "huge_field": b"freq_hz,magnitude,phase_deg,magnitude_std,phase_std_deg\n\"" + b"1" * 200_000 + b"\",2,3,4,5\n",
    "json": b'{"schema": "torchblur.sysid.frequency_response"}',
}


@pytest.mark.parametrize("case", list(BAD_CSV))
def test_bad_frf_csv_is_one_error_naming_the_path(case, tmp_path):
    path = tmp_path / "frf.csv"
    path.write_bytes(BAD_CSV[case])
    with pytest.raises(TorchblurError) as info:
        FrequencyResponse.from_csv(path)
    assert isinstance(info.value, (ParameterError, InputTypeError, ShapeError))
    assert str(path) in str(info.value)
