/*
 * The board's reporting logic, shared by every board layer and the host simulator:
 * which frame is due when, sequence numbers, fault bits.
 *
 * Portable C99: no OS, no malloc, no clock of its own. The board layer owns the
 * pins, the clock and the link; it calls bridge_poll() with the time and a copy of
 * the two decoders (taken with interrupts masked) and sends what comes back, one
 * frame per call:
 *
 *     while ((n = bridge_poll(&b, now_us, &left, &right, buf, sizeof buf)) > 0)
 *         if (!link_send(buf, n)) bridge_frame_dropped(&b, host_attached);
 *
 * Schedule: CONFIG_ECHO at the first poll, on bridge_request_config() and every
 * BRIDGE_CONFIG_PERIOD_MS; HEARTBEAT every heartbeat_period_ms; TICKS at tick_rate_hz,
 * all starting at the first poll. When several are due at one poll they go out in
 * that order (CONFIG_ECHO, HEARTBEAT, TICKS), each stamped with the poll's time.
 * A poll late by a whole TICKS period or more sends one TICKS frame for the missed
 * slots, keeps the original time grid and latches LOOP_OVERRUN.
 */
#ifndef TREETRAITS_BRIDGE_H
#define TREETRAITS_BRIDGE_H

#include <stddef.h>
#include <stdint.h>

#include "frame.h"
#include "quadrature.h"

#define BRIDGE_FW_MAJOR 1u
#define BRIDGE_FW_MINOR 0u
#define BRIDGE_FW_PATCH 0u

#define BRIDGE_CONFIG_PERIOD_MS 10000u

typedef struct {
    bridge_config_t config;
    uint8_t board;
    uint8_t started;
    uint16_t seq; /* of the next frame; every frame built takes one, sent or not */
    uint16_t boot_id;
    uint32_t faults_latched;
    uint32_t faults_sticky;
    uint32_t tx_dropped;
    uint32_t seen_errors[2]; /* decoder error counts at the previous heartbeat */
    uint64_t next_ticks_us;
    uint64_t next_heartbeat_us;
    uint64_t next_config_us;
} bridge_t;

/* `config->tick_rate_hz` in 1..1000 and `heartbeat_period_ms` >= 1; `boot_id` a random
 * number drawn at boot; `sticky_faults` the reset-cause bits this boot began with. */
void bridge_init(bridge_t *b, const bridge_config_t *config, uint8_t board, uint16_t boot_id,
                 uint32_t sticky_faults);

/* The earliest time a frame is due (0 before the first poll). */
uint64_t bridge_next_due(const bridge_t *b);

/* Send CONFIG_ECHO at the next poll (a host has just opened the port). */
void bridge_request_config(bridge_t *b);

/* The frame last returned by bridge_poll() could not be sent. `host_attached`: the
 * link was up but full (latches TX_OVERFLOW), rather than nobody listening. */
void bridge_frame_dropped(bridge_t *b, int host_attached);

/* Build the next frame due at `now_us` into `out`; 0 when nothing is due (or `cap` is
 * less than BRIDGE_MAX_WIRE). */
size_t bridge_poll(bridge_t *b, uint64_t now_us, const quad_t *left, const quad_t *right,
                   uint8_t *out, size_t cap);

#endif
