"""`resolve_device`: known types only, present devices only, errors naming the option and the fix;
and the argparse converters of `mvgeo.common.argtypes`."""

import argparse
import subprocess
import sys

import pytest
import torch

from mvgeo.common.argtypes import SEED_MAX, fraction, int_range, nonneg_int, positive_float, positive_int, seed, size_wh
from mvgeo.common.device import resolve_device
from mvgeo.common.errors import InputError


@pytest.fixture
def one_gpu(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)


def test_cpu_and_auto_without_cuda(no_cuda):
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device(" CPU ") == torch.device("cpu")
    assert resolve_device("auto") == torch.device("cpu")


def test_auto_with_cuda(one_gpu):
    assert resolve_device("auto") == torch.device("cuda")


@pytest.mark.parametrize("text", ["cudaa", "banana", "", "cuda:", "cuda:x", "cuda:-1", "gpu", "mps:1", "auto:0",
                                  "cuda 0"])
def test_unknown_device_names_the_option(text):
    with pytest.raises(InputError) as info:
        resolve_device(text, option="--device")
    msg = str(info.value)
    assert "--device" in msg and "unknown device" in msg
    assert info.value.fix and "cpu" in info.value.fix


@pytest.mark.parametrize("text", ["cuda", "cuda:0", "CUDA:1"])
def test_cuda_absent_is_refused(no_cuda, text):
    with pytest.raises(InputError) as info:
        resolve_device(text)
    assert "CUDA is not available" in str(info.value) and "--device" in str(info.value)
    assert "cpu" in info.value.fix


def test_cuda_index_must_exist(one_gpu):
    assert resolve_device("cuda") == torch.device("cuda")
    assert resolve_device("cuda:0") == torch.device("cuda", 0)
    with pytest.raises(InputError) as info:
        resolve_device("cuda:3")
    assert "1 CUDA device" in str(info.value) and "cuda:3" in str(info.value)


def test_mps_absent_is_refused(monkeypatch):
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: False)
    with pytest.raises(InputError, match="MPS"):
        resolve_device("mps")


def test_importing_the_helper_does_not_import_torch():
    code = "import sys, mvgeo.common.device, mvgeo.common.argtypes; assert 'torch' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)


# -- argtypes -----------------------------------------------------------------------------------------


@pytest.mark.parametrize(("convert", "good", "bad"), [
    (positive_int, {"1": 1, "12": 12}, ["0", "-2", "1.5", "x", ""]),
    (nonneg_int, {"0": 0, "7": 7}, ["-1", "one"]),
    (int_range(16), {"16": 16, "512": 512}, ["15", "0"]),
    (int_range(2, 5), {"2": 2, "5": 5}, ["1", "6"]),
    (seed, {"0": 0, str(SEED_MAX): SEED_MAX}, ["-1", str(SEED_MAX + 1)]),
    (positive_float, {"0.5": 0.5, "3": 3.0}, ["0", "-1", "nan", "inf", "x"]),
    (fraction, {"0": 0.0, "1": 1.0, "0.25": 0.25}, ["-0.1", "1.01", "nan"]),
])
def test_numeric_converters(convert, good, bad):
    for text, value in good.items():
        assert convert(text) == value
    for text in bad:
        with pytest.raises(argparse.ArgumentTypeError):
            convert(text)


def test_size_wh():
    convert = size_wh(8, 8192)
    assert convert("504x378") == (504, 378)
    assert convert(" 8 X 8192 ") == (8, 8192)
    for text in ["0x5", "5x0", "7x100", "100x8193", "504", "504x", "x378", "-5x5", "5.5x5"]:
        with pytest.raises(argparse.ArgumentTypeError):
            convert(text)


def test_parser_reports_the_option(capsys):
    p = argparse.ArgumentParser(prog="t")
    p.add_argument("--depth-stride", type=positive_int, default=4)
    with pytest.raises(SystemExit) as info:
        p.parse_args(["--depth-stride", "0"])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "argument --depth-stride: must be an integer >= 1, got '0'" in err
