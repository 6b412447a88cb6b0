/*
 * Build-time configuration of the magcal firmware library: every knob is a -D flag with the
 * default below. Each module has its own section.
 */
#ifndef MAGCAL_CONFIG_H
#define MAGCAL_CONFIG_H

/* ---- correction and parameter validation (correction.h, params.h) ---- */

/* ---- parameter storage (storage.h, flash.h) ---- */

/* ---- acquisition (acquire.h, ring.h) ---- */

/* ---- protocol endpoint (frame.h, dispatch.h) ---- */

#endif /* MAGCAL_CONFIG_H */
