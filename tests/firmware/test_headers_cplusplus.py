# SPDX-License-Identifier: Apache-2.0
"""The public headers work from C++: each one compiles on its own in a C++11 translation unit
without a warning, and their functions keep C linkage (``extern "C"``), so a C++ program links
against the library that gcc built as C99."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
INCLUDE = REPO_ROOT / "firmware" / "include"
HEADERS = sorted((INCLUDE / "magcal").glob("*.h"))
CXX_FLAGS = ["-std=c++11", "-Wall", "-Wextra", "-Werror", f"-I{INCLUDE}"]
COMPILE_TIMEOUT_S = 120
RUN_TIMEOUT_S = 30


def gxx() -> str:
    path = shutil.which("g++")
    if path is None:
        pytest.skip("g++ is not installed: the C++ checks of the public headers need it")
    return path


def compile_cpp(tmp_path: Path, source: str, *extra: str) -> subprocess.CompletedProcess:
    cpp = tmp_path / "check.cpp"
    cpp.write_text(source, encoding="utf-8")
    return subprocess.run(
        [gxx(), *CXX_FLAGS, str(cpp), *extra],  # libraries after the source that uses them
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=COMPILE_TIMEOUT_S,
    )


def test_the_public_headers_are_found():
    names = {h.name for h in HEADERS}
    assert {"status.h", "messages.h", "device.h", "version.h"} <= names


@pytest.mark.parametrize("header", HEADERS, ids=lambda h: h.name)
def test_header_has_c_linkage_guards(header):
    text = header.read_text(encoding="utf-8")
    opening = '#ifdef __cplusplus\nextern "C" {\n#endif\n'
    closing = "#ifdef __cplusplus\n}\n#endif\n"
    assert text.count(opening) == 1, f'{header.name}: no extern "C" opening block'
    assert text.count(closing) == 1, f'{header.name}: no extern "C" closing block'
    assert text.index(opening) < text.index(closing)


@pytest.mark.parametrize("header", HEADERS, ids=lambda h: h.name)
def test_header_compiles_alone_as_cplusplus(tmp_path, header):
    r = compile_cpp(tmp_path, f'#include "magcal/{header.name}"\n', "-fsyntax-only")
    assert r.returncode == 0, f"{header.name} in C++11:\n{r.stderr}"


def test_all_headers_together_as_cplusplus(tmp_path):
    source = "".join(f'#include "magcal/{h.name}"\n' for h in HEADERS)
    r = compile_cpp(tmp_path, source, "-fsyntax-only")
    assert r.returncode == 0, r.stderr


def test_cplusplus_program_links_against_the_c_library(tmp_path, fwlib):
    """Without the guards g++ would look for mangled names and the link would fail. Each
    module's function is called with arguments it refuses, or with the CRC check value."""
    source = r"""
#include <cstdio>
#include <cstring>

#include "magcal/acquire.h"
#include "magcal/correction.h"
#include "magcal/crc.h"
#include "magcal/device.h"
#include "magcal/frame.h"
#include "magcal/messages.h"
#include "magcal/params.h"
#include "magcal/ring.h"
#include "magcal/sensor_hal.h"
#include "magcal/storage.h"
#include "magcal/version.h"

int main()
{
    const char *check = "123456789";
    int bad = 0;
    bad += mc_crc16_ccitt_false(reinterpret_cast<const uint8_t *>(check), 9) != 0x29B1;
    bad += std::strcmp(mc_msg_name(MC_MSG_HELLO), "hello") != 0;
    bad += mc_params_validate(NULL) != MC_E_ARG;
    bad += mc_correction_init(NULL, NULL) != MC_E_ARG;
    bad += mc_ring_init(NULL, NULL, 0) != MC_E_ARG;
    bad += mc_frame_decoder_init(NULL, NULL, 0) != MC_E_ARG;
    bad += mc_sensor_info_check(NULL, MC_SENSOR_MAG) != MC_E_ARG;
    bad += mc_storage_init(NULL, NULL, 0, 0, 0) != MC_E_ARG;
    bad += mc_acquire_init(NULL, NULL, NULL, 0, 0) != MC_E_ARG;
    bad += mc_device_init(NULL, NULL) != MC_E_ARG;
    std::printf("%s %d\n", MAGCAL_VERSION_STRING, bad);
    return bad != 0;
}
"""
    lib = Path(fwlib._name)
    r = compile_cpp(tmp_path, source, "-o", "check", str(lib), f"-Wl,-rpath,{lib.parent}")
    assert r.returncode == 0, r.stderr
    run = subprocess.run(
        [str(tmp_path / "check")], capture_output=True, text=True, timeout=RUN_TIMEOUT_S
    )
    assert run.returncode == 0, run.stdout + run.stderr
    assert run.stdout.split()[1] == "0"
