# SPDX-License-Identifier: Apache-2.0
# The device protocol: code generation from protocol/schema.json and the frame decoder's
# libFuzzer target. Included by the root Makefile after FW_SRC, FW_HDR, FW_WARN and FW_INC.
#
#   make generate     regenerate the committed C headers, messages.c, generated.py and the
#                     golden vectors from protocol/schema.json (protocol/generate.py)
#   make check-generated   the committed output is what the generator gives (also a pytest
#                     test: tests/protocol/test_generated_up_to_date.py)
#   make fuzz-smoke   build firmware/fuzz/fuzz_frame_decoder.c with clang's libFuzzer, ASan and
#                     UBSan, and run it for FUZZ_SECONDS from a seed corpus of the vectors

.PHONY: generate check-generated fuzz-smoke

PROTOCOL_GEN := protocol/generate.py
FUZZ_SECONDS ?= 30
FUZZ_DIR := build/fuzz

generate:
	$(PYTHON) $(PROTOCOL_GEN)

check-generated:
	@rm -rf $(FUZZ_DIR)/generated && mkdir -p $(FUZZ_DIR)/generated
	$(PYTHON) $(PROTOCOL_GEN) --out $(FUZZ_DIR)/generated
	@set -e; cd $(FUZZ_DIR)/generated && for f in $$(find . -type f | sort); do \
		diff -u "$(CURDIR)/$$f" "$$f" || { echo "check-generated: $$f differs from the schema's output: run make generate" >&2; exit 1; }; \
	done; echo "check-generated: up to date"

# The native frame test includes the generated vectors.
build/native/test_fw_frame build/native/test_fw_messages: protocol/vectors/vectors.h

$(FUZZ_DIR)/fuzz_frame_decoder: firmware/fuzz/fuzz_frame_decoder.c $(FW_SRC) $(FW_HDR)
	@mkdir -p $(@D)
	@command -v clang >/dev/null 2>&1 || { echo "fuzz-smoke: clang is not installed: run make deps-target (installs clang and its libFuzzer runtime)" >&2; exit 1; }
	@printf 'int LLVMFuzzerTestOneInput(const unsigned char *d, unsigned long n) { (void)d; (void)n; return 0; }\n' > $(@D)/probe.c
	@clang -fsanitize=fuzzer,address,undefined $(@D)/probe.c -o $(@D)/probe 2>/dev/null || { echo "fuzz-smoke: clang cannot link -fsanitize=fuzzer,address,undefined (libFuzzer/sanitizer runtime missing, Debian package libclang-rt-<version>-dev): run make deps-target" >&2; exit 1; }
	clang $(FW_WARN) -O1 -g -fsanitize=fuzzer,address,undefined -fno-sanitize-recover=all \
		$(FW_INC) firmware/fuzz/fuzz_frame_decoder.c $(FW_SRC) -o $@

fuzz-smoke: $(FUZZ_DIR)/fuzz_frame_decoder
	@rm -rf $(FUZZ_DIR)/seeds && mkdir -p $(FUZZ_DIR)/corpus
	$(PYTHON) $(PROTOCOL_GEN) --corpus $(FUZZ_DIR)/seeds
	$(FUZZ_DIR)/fuzz_frame_decoder -max_total_time=$(FUZZ_SECONDS) -max_len=1024 \
		-print_final_stats=1 $(FUZZ_DIR)/corpus $(FUZZ_DIR)/seeds

TEST_EXTRA += fuzz-smoke
