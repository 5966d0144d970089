/* Protocol v1 framing: CRC-32C, COBS, little-endian packing. See frame.h. */
#include "frame.h"

uint32_t bridge_crc32c(const uint8_t *data, size_t len)
{
    /* Bitwise: a frame is at most 250 bytes at ~110 frames/s, so a table buys nothing. */
    uint32_t crc = 0xFFFFFFFFul;
    size_t i;
    int bit;
    for (i = 0; i < len; i++) {
        crc ^= data[i];
        for (bit = 0; bit < 8; bit++) {
            crc = (crc & 1u) ? (crc >> 1) ^ 0x82F63B78ul : crc >> 1;
        }
    }
    return crc ^ 0xFFFFFFFFul;
}

size_t bridge_cobs_encode(const uint8_t *in, size_t len, uint8_t *out)
{
    size_t code_at = 0; /* where the current block's code byte goes */
    size_t o = 1;
    uint8_t code = 1; /* 1 + data bytes in the current block */
    size_t i;
    for (i = 0; i < len; i++) {
        if (in[i] == 0) {
            out[code_at] = code;
            code_at = o++;
            code = 1;
        } else {
            out[o++] = in[i];
            code++;
            if (code == 0xFF && i + 1 < len) { /* a full block: no zero implied after it */
                out[code_at] = code;
                code_at = o++;
                code = 1;
            }
        }
    }
    out[code_at] = code;
    return o;
}

static void put_u16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)(v & 0xFFu);
    p[1] = (uint8_t)(v >> 8);
}

static void put_u32(uint8_t *p, uint32_t v)
{
    int i;
    for (i = 0; i < 4; i++) {
        p[i] = (uint8_t)((v >> (8 * i)) & 0xFFu);
    }
}

static void put_u64(uint8_t *p, uint64_t v)
{
    int i;
    for (i = 0; i < 8; i++) {
        p[i] = (uint8_t)((v >> (8 * i)) & 0xFFu);
    }
}

size_t bridge_encode_frame(uint8_t type, const bridge_stamp_t *stamp, const uint8_t *payload,
                           size_t payload_len, uint8_t *out, size_t cap)
{
    uint8_t frame[BRIDGE_MAX_FRAME];
    size_t len = BRIDGE_HEADER_SIZE + payload_len;
    size_t i;
    size_t n;
    if (payload_len > BRIDGE_MAX_PAYLOAD) {
        return 0;
    }
    /* Worst case for a frame of up to 254 bytes: one COBS overhead byte + 2 delimiters. */
    if (cap < len + BRIDGE_CRC_SIZE + 3u) {
        return 0;
    }
    frame[0] = (uint8_t)BRIDGE_PROTOCOL_VERSION;
    frame[1] = type;
    put_u16(frame + 2, stamp->seq);
    put_u16(frame + 4, stamp->boot_id);
    put_u64(frame + 6, stamp->t_us);
    for (i = 0; i < payload_len; i++) {
        frame[BRIDGE_HEADER_SIZE + i] = payload[i];
    }
    put_u32(frame + len, bridge_crc32c(frame, len));
    len += BRIDGE_CRC_SIZE;

    out[0] = 0x00; /* ends whatever partial frame the host holds (noise, a reset) */
    n = bridge_cobs_encode(frame, len, out + 1);
    out[1 + n] = 0x00;
    return n + 2;
}

size_t bridge_encode_ticks(const bridge_stamp_t *stamp, const bridge_ticks_t *m, uint8_t *out,
                           size_t cap)
{
    uint8_t p[BRIDGE_TICKS_SIZE];
    put_u32(p + 0, m->left);
    put_u32(p + 4, m->right);
    put_u32(p + 8, m->left_errors);
    put_u32(p + 12, m->right_errors);
    return bridge_encode_frame(BRIDGE_MSG_TICKS, stamp, p, sizeof p, out, cap);
}

size_t bridge_encode_heartbeat(const bridge_stamp_t *stamp, const bridge_heartbeat_t *m,
                               uint8_t *out, size_t cap)
{
    uint8_t p[BRIDGE_HEARTBEAT_SIZE];
    put_u32(p + 0, m->faults);
    put_u32(p + 4, m->tx_dropped);
    p[8] = m->fw_major;
    p[9] = m->fw_minor;
    p[10] = m->fw_patch;
    p[11] = m->board;
    return bridge_encode_frame(BRIDGE_MSG_HEARTBEAT, stamp, p, sizeof p, out, cap);
}

size_t bridge_encode_config_echo(const bridge_stamp_t *stamp, const bridge_config_t *m,
                                 uint8_t *out, size_t cap)
{
    uint8_t p[BRIDGE_CONFIG_ECHO_SIZE];
    put_u32(p + 0, m->ticks_per_rev);
    put_u16(p + 4, m->tick_rate_hz);
    put_u16(p + 6, m->heartbeat_period_ms);
    p[8] = m->flags;
    return bridge_encode_frame(BRIDGE_MSG_CONFIG_ECHO, stamp, p, sizeof p, out, cap);
}
