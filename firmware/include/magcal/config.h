/* SPDX-License-Identifier: Apache-2.0 */
/*
 * Build-time configuration of the magcal firmware library: every knob is a -D flag with the
 * default below. Each module has its own section.
 */
#ifndef MAGCAL_CONFIG_H
#define MAGCAL_CONFIG_H

#ifdef __cplusplus
extern "C" {
#endif

/* ---- correction and parameter validation (correction.h, params.h) ---- */

/* Largest condition number kappa_inf(D^-1) = ||D^-1||_inf ||D||_inf that mc_params_validate
 * accepts (MC_E_CONDITION above it). A magnetometer calibration is close to a scaled rotation
 * (kappa_inf of 1 to about 3); 100 leaves room for strongly distorted sensors while refusing a
 * nearly singular D^-1. An integer in [1, 1000000]; the host's fixed_point.COND_MAX must match. */
#ifndef MC_PARAMS_COND_MAX
#define MC_PARAMS_COND_MAX 100u
#endif
#if MC_PARAMS_COND_MAX < 1 || MC_PARAMS_COND_MAX > 1000000
#error "MC_PARAMS_COND_MAX must be in [1, 1000000]"
#endif

/* ---- parameter storage (storage.h, flash.h) ---- */

/* Largest payload (an encoded parameter set) mc_storage_commit accepts, in bytes. A slot must
 * hold MC_STORAGE_RECORD_SIZE(MC_STORAGE_PAYLOAD_MAX) bytes (152 with the default), which
 * mc_storage_init checks. */
#ifndef MC_STORAGE_PAYLOAD_MAX
#define MC_STORAGE_PAYLOAD_MAX 128u
#endif
#if MC_STORAGE_PAYLOAD_MAX < 1
#error "MC_STORAGE_PAYLOAD_MAX must be at least 1"
#endif

/* Bytes storage.c reads from flash per read call while checking a slot (a stack buffer of
 * this size): larger is fewer driver calls, smaller is less stack. A multiple of 4. */
#ifndef MC_STORAGE_READ_CHUNK
#define MC_STORAGE_READ_CHUNK 32u
#endif
#if MC_STORAGE_READ_CHUNK < 4 || MC_STORAGE_READ_CHUNK % 4 != 0
#error "MC_STORAGE_READ_CHUNK must be a non-zero multiple of 4"
#endif

/* ---- acquisition (acquire.h, ring.h) ---- */

/* Capacity of the acquisition ring in samples (ring.h, acquire.h): a power of two. The ports
 * size their mc_sample_t array with it; one sample is 32 bytes, so 64 samples are 2 KB and
 * hold 0.64 s at 100 Hz. */
#ifndef MC_RING_CAPACITY
#define MC_RING_CAPACITY 64u
#endif
#if MC_RING_CAPACITY < 1 || (MC_RING_CAPACITY & (MC_RING_CAPACITY - 1)) != 0
#error "MC_RING_CAPACITY must be a power of two"
#endif

/* Barrier between a ring slot's contents and the index that publishes it (ring.c). The default
 * is a compiler barrier, enough on a single core (Cortex-M4) where the producer is an
 * interrupt; define it as a hardware barrier (e.g. __DMB()) when the producer runs on another
 * core or is a DMA engine. */
#ifndef MC_RING_BARRIER
#if defined(__GNUC__) || defined(__clang__)
#define MC_RING_BARRIER() __asm__ __volatile__("" ::: "memory")
#else
#error "define MC_RING_BARRIER() as a compiler barrier for this compiler"
#endif
#endif

/* ---- protocol endpoint (frame.h, messages.h, device.h) ----
 * No knobs: frame and payload sizes are protocol constants both sides must agree on, so they
 * come from protocol/schema.json through the generated messages.h, not from -D flags. */

#ifdef __cplusplus
}
#endif

#endif /* MAGCAL_CONFIG_H */
