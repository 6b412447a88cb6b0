# SPDX-License-Identifier: Apache-2.0
# The software-in-the-loop device: the firmware library's protocol endpoint (device.h) as a
# native process, build/sil/magcal-sil (firmware/port/posix/sil_main.c documents its
# interface). Included by the root Makefile after FW_SRC, FW_HDR, FW_WARN and FW_INC.
#
#   make sil    build/sil/magcal-sil (-Werror); tests/sil drives it from pytest

.PHONY: sil

SIL_DIR := build/sil
SIL_BIN := $(SIL_DIR)/magcal-sil
SIL_SRC := firmware/port/posix/sil_main.c firmware/port/posix/flash_file.c \
	firmware/port/posix/sensor_feed.c
# info's fw_build: the first 32 bits of the commit id, 0 outside a git checkout.
SIL_FW_BUILD := 0x$(or $(shell git rev-parse --short=8 HEAD 2>/dev/null),0)

sil: $(SIL_BIN)

$(SIL_BIN): $(SIL_SRC) $(wildcard firmware/port/posix/*.h) firmware/port/demo_sensors.h $(FW_SRC) $(FW_HDR) mk/sil.mk
	@mkdir -p $(@D)
	gcc $(FW_WARN) -O2 -g $(FW_INC) -Ifirmware/port/posix -DMC_SIL_FW_BUILD=$(SIL_FW_BUILD)u \
		$(SIL_SRC) $(FW_SRC) -o $@

TEST_EXTRA += sil
