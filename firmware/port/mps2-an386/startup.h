/* SPDX-License-Identifier: Apache-2.0 */
/* Hooks of startup.c for the application. */
#ifndef MAGCAL_PORT_STARTUP_H
#define MAGCAL_PORT_STARTUP_H

#include <stdint.h>

/* Called from the default handler with the exception number (IPSR: 2 NMI, 3 HardFault,
 * 16 + n for interrupt n) before it spins forever. Weak: the default does nothing; the
 * application may report the fault (it runs in handler mode, so it must poll, not wait
 * for interrupts). */
void mc_startup_on_fault(uint32_t exception);

#endif /* MAGCAL_PORT_STARTUP_H */
