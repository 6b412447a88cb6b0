/* SPDX-License-Identifier: Apache-2.0 */
/*
 * The firmware library's version: the same as the host package's (host/pyproject.toml), so a
 * release is one version on both sides; tests/firmware/test_version.py checks that they agree.
 *
 * The numbers are plain decimal integers, usable in #if:
 *
 *     #if MAGCAL_VERSION_MAJOR == 0 && MAGCAL_VERSION_MINOR < 2
 *
 * A device port's own firmware version (info_resp.fw_version) is the port's to choose.
 */
#ifndef MAGCAL_VERSION_H
#define MAGCAL_VERSION_H

#ifdef __cplusplus
extern "C" {
#endif

#define MAGCAL_VERSION_MAJOR 0
#define MAGCAL_VERSION_MINOR 1
#define MAGCAL_VERSION_PATCH 0
/* "MAJOR.MINOR.PATCH" of the three above. */
#define MAGCAL_VERSION_STRING "0.1.0"

#ifdef __cplusplus
}
#endif

#endif /* MAGCAL_VERSION_H */
