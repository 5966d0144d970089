/*
 * Retrofit bridge protocol v1 (firmware_bridge/PROTOCOL.md): CRC-32C, COBS and
 * message packing into a caller's buffer.
 *
 * Portable C99: no OS, no malloc. Every function writes only into the buffer it
 * is given and returns the number of bytes written, or 0 when the buffer is too
 * small (nothing useful is written then).
 *
 * A frame on the wire is 0x00, COBS(header + payload + CRC-32C), 0x00.
 */
#ifndef TREETRAITS_FRAME_H
#define TREETRAITS_FRAME_H

#include <stddef.h>
#include <stdint.h>

#define BRIDGE_PROTOCOL_VERSION 1u

#define BRIDGE_MSG_TICKS 0x01u
#define BRIDGE_MSG_HEARTBEAT 0x02u
#define BRIDGE_MSG_CONFIG_ECHO 0x03u

#define BRIDGE_HEADER_SIZE 14u /* version u8, type u8, seq u16, boot_id u16, t_us u64 */
#define BRIDGE_CRC_SIZE 4u
#define BRIDGE_MAX_FRAME 254u /* header + payload + CRC: one COBS block at most */
#define BRIDGE_MAX_PAYLOAD (BRIDGE_MAX_FRAME - BRIDGE_HEADER_SIZE - BRIDGE_CRC_SIZE)
/* Leading 0x00, COBS overhead byte, trailing 0x00. */
#define BRIDGE_MAX_WIRE (BRIDGE_MAX_FRAME + 3u)

#define BRIDGE_TICKS_SIZE 16u
#define BRIDGE_HEARTBEAT_SIZE 12u
#define BRIDGE_CONFIG_ECHO_SIZE 9u

/* HEARTBEAT fault bits. "Latched" bits report what happened since the previous
 * heartbeat and are cleared once one is built; "sticky" bits hold for the boot. */
#define BRIDGE_FAULT_LEFT_GLITCH (1ul << 0)     /* latched: illegal A/B step, left */
#define BRIDGE_FAULT_RIGHT_GLITCH (1ul << 1)    /* latched: illegal A/B step, right */
#define BRIDGE_FAULT_TX_OVERFLOW (1ul << 2)     /* latched: frame dropped, link full */
#define BRIDGE_FAULT_LOOP_OVERRUN (1ul << 3)    /* latched: a TICKS period was skipped */
#define BRIDGE_FAULT_WATCHDOG_RESET (1ul << 4)  /* sticky: this boot began with a watchdog reset */
#define BRIDGE_FAULT_BROWNOUT_RESET (1ul << 5)  /* sticky: this boot began with a brown-out */
#define BRIDGE_FAULT_CONFIG_DEFAULTS (1ul << 6) /* sticky: stored config invalid, defaults used */

/* CONFIG_ECHO flags. */
#define BRIDGE_CONFIG_INVERT_LEFT (1u << 0)
#define BRIDGE_CONFIG_INVERT_RIGHT (1u << 1)

/* HEARTBEAT board kinds. */
#define BRIDGE_BOARD_HOST_SIM 0u
#define BRIDGE_BOARD_RP2040 1u

/* The header fields a sender chooses. */
typedef struct {
    uint16_t seq;     /* +1 per frame built, wraps */
    uint16_t boot_id; /* random at boot: a change tells the host the board restarted */
    uint64_t t_us;    /* board clock, us since boot, when the content was sampled */
} bridge_stamp_t;

typedef struct {
    uint32_t left;  /* cumulative count, int32 two's complement bits */
    uint32_t right;
    uint32_t left_errors; /* cumulative illegal transitions */
    uint32_t right_errors;
} bridge_ticks_t;

typedef struct {
    uint32_t faults;
    uint32_t tx_dropped; /* cumulative frames built but not sent */
    uint8_t fw_major;
    uint8_t fw_minor;
    uint8_t fw_patch;
    uint8_t board;
} bridge_heartbeat_t;

typedef struct {
    uint32_t ticks_per_rev; /* 4x counts per wheel revolution */
    uint16_t tick_rate_hz;
    uint16_t heartbeat_period_ms;
    uint8_t flags;
} bridge_config_t;

/* CRC-32C (Castagnoli): reflected polynomial 0x82F63B78, init and xorout 0xFFFFFFFF.
 * bridge_crc32c("123456789", 9) == 0xE3069283. */
uint32_t bridge_crc32c(const uint8_t *data, size_t len);

/* COBS (Cheshire & Baker 1999) of `len` bytes into `out`, which must hold
 * len + len / 254 + 1 bytes. Returns the encoded length. Data ending in a full
 * 254-byte block gets no extra code byte after it (FF + 254 bytes, then the end). */
size_t bridge_cobs_encode(const uint8_t *in, size_t len, uint8_t *out);

/* One whole frame as it goes on the wire (0x00, COBS, 0x00). */
size_t bridge_encode_frame(uint8_t type, const bridge_stamp_t *stamp, const uint8_t *payload,
                           size_t payload_len, uint8_t *out, size_t cap);

size_t bridge_encode_ticks(const bridge_stamp_t *stamp, const bridge_ticks_t *m, uint8_t *out,
                           size_t cap);
size_t bridge_encode_heartbeat(const bridge_stamp_t *stamp, const bridge_heartbeat_t *m,
                               uint8_t *out, size_t cap);
size_t bridge_encode_config_echo(const bridge_stamp_t *stamp, const bridge_config_t *m,
                                 uint8_t *out, size_t cap);

#endif
