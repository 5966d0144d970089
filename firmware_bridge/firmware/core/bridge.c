/* The board's reporting schedule and fault bits: see bridge.h. */
#include "bridge.h"

void bridge_init(bridge_t *b, const bridge_config_t *config, uint8_t board, uint16_t boot_id,
                 uint32_t sticky_faults)
{
    b->config = *config;
    b->board = board;
    b->started = 0;
    b->seq = 0;
    b->boot_id = boot_id;
    b->faults_latched = 0;
    b->faults_sticky = sticky_faults;
    b->tx_dropped = 0;
    b->seen_errors[0] = 0;
    b->seen_errors[1] = 0;
    b->next_ticks_us = 0;
    b->next_heartbeat_us = 0;
    b->next_config_us = 0;
}

static uint64_t min_u64(uint64_t a, uint64_t b)
{
    return a < b ? a : b;
}

uint64_t bridge_next_due(const bridge_t *b)
{
    if (!b->started) {
        return 0;
    }
    return min_u64(b->next_ticks_us, min_u64(b->next_heartbeat_us, b->next_config_us));
}

void bridge_request_config(bridge_t *b)
{
    b->next_config_us = 0;
}

void bridge_frame_dropped(bridge_t *b, int host_attached)
{
    b->tx_dropped++;
    if (host_attached) {
        b->faults_latched |= BRIDGE_FAULT_TX_OVERFLOW;
    }
}

/* The next slot on the grid `due + k * period` that is after `now`. */
static uint64_t next_slot(uint64_t due, uint64_t period, uint64_t now)
{
    if (now < due) {
        return due;
    }
    return due + ((now - due) / period + 1u) * period;
}

size_t bridge_poll(bridge_t *b, uint64_t now_us, const quad_t *left, const quad_t *right,
                   uint8_t *out, size_t cap)
{
    uint64_t tick_period = 1000000u / b->config.tick_rate_hz;
    uint64_t heartbeat_period = 1000u * (uint64_t)b->config.heartbeat_period_ms;
    bridge_stamp_t stamp;
    size_t n;

    if (cap < BRIDGE_MAX_WIRE) {
        return 0;
    }
    if (!b->started) { /* the time grid starts at the first poll */
        b->started = 1;
        b->next_ticks_us = now_us;
        b->next_heartbeat_us = now_us;
        b->next_config_us = now_us;
    }
    stamp.seq = b->seq;
    stamp.boot_id = b->boot_id;
    stamp.t_us = now_us;

    if (b->next_config_us <= now_us) {
        n = bridge_encode_config_echo(&stamp, &b->config, out, cap);
        b->seq++;
        b->next_config_us = now_us + 1000u * (uint64_t)BRIDGE_CONFIG_PERIOD_MS;
        return n;
    }

    if (b->next_heartbeat_us <= now_us) {
        bridge_heartbeat_t hb;
        uint32_t faults = b->faults_latched | b->faults_sticky;
        if (left->errors != b->seen_errors[0]) {
            faults |= BRIDGE_FAULT_LEFT_GLITCH;
        }
        if (right->errors != b->seen_errors[1]) {
            faults |= BRIDGE_FAULT_RIGHT_GLITCH;
        }
        hb.faults = faults;
        hb.tx_dropped = b->tx_dropped;
        hb.fw_major = (uint8_t)BRIDGE_FW_MAJOR;
        hb.fw_minor = (uint8_t)BRIDGE_FW_MINOR;
        hb.fw_patch = (uint8_t)BRIDGE_FW_PATCH;
        hb.board = b->board;
        n = bridge_encode_heartbeat(&stamp, &hb, out, cap);
        b->seq++;
        b->seen_errors[0] = left->errors;
        b->seen_errors[1] = right->errors;
        b->faults_latched = 0;
        b->next_heartbeat_us = next_slot(b->next_heartbeat_us, heartbeat_period, now_us);
        return n;
    }

    if (b->next_ticks_us <= now_us) {
        bridge_ticks_t t;
        if (now_us - b->next_ticks_us >= tick_period) {
            b->faults_latched |= BRIDGE_FAULT_LOOP_OVERRUN;
        }
        t.left = left->count;
        t.right = right->count;
        t.left_errors = left->errors;
        t.right_errors = right->errors;
        n = bridge_encode_ticks(&stamp, &t, out, cap);
        b->seq++;
        b->next_ticks_us = next_slot(b->next_ticks_us, tick_period, now_us);
        return n;
    }
    return 0;
}
