/*
 * Retrofit encoder board on a Raspberry Pi Pico (RP2040) with the pico-sdk (>= 1.5).
 *
 * Two quadrature encoders on GPIO pin-change interrupts, protocol v1 frames over USB
 * CDC. Everything the protocol says is in ../../core (the code the host tests run);
 * this file only owns the pins, the clock, the watchdog and the USB link.
 * Build and wiring: README.md beside this file.
 */
#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "hardware/gpio.h"
#include "hardware/sync.h"
#include "hardware/watchdog.h"
#include "pico/rand.h"
#include "pico/stdio_usb.h"
#include "pico/stdlib.h"
#include "tusb.h"

#include "bridge.h"

/* Build-time configuration (CMake cache variables of the same names). */
#ifndef BRIDGE_PIN_LEFT_A
#define BRIDGE_PIN_LEFT_A 2
#endif
#ifndef BRIDGE_PIN_LEFT_B
#define BRIDGE_PIN_LEFT_B 3
#endif
#ifndef BRIDGE_PIN_RIGHT_A
#define BRIDGE_PIN_RIGHT_A 4
#endif
#ifndef BRIDGE_PIN_RIGHT_B
#define BRIDGE_PIN_RIGHT_B 5
#endif
#ifndef BRIDGE_TICKS_PER_REV
#define BRIDGE_TICKS_PER_REV 4096
#endif
#ifndef BRIDGE_TICK_RATE_HZ
#define BRIDGE_TICK_RATE_HZ 100
#endif
#ifndef BRIDGE_HEARTBEAT_MS
#define BRIDGE_HEARTBEAT_MS 1000
#endif
#ifndef BRIDGE_INVERT_LEFT
#define BRIDGE_INVERT_LEFT 0
#endif
#ifndef BRIDGE_INVERT_RIGHT
#define BRIDGE_INVERT_RIGHT 0
#endif

#define WATCHDOG_MS 100u
#define EDGES (GPIO_IRQ_EDGE_RISE | GPIO_IRQ_EDGE_FALL)

/* Written only by the GPIO interrupt; the main loop copies them with interrupts off. */
static quad_t left_encoder;
static quad_t right_encoder;

static int level(uint32_t pins, uint pin)
{
    return (int)((pins >> pin) & 1u);
}

static void on_edge(uint gpio, uint32_t events)
{
    /* Read both pins of the pair at once: an edge we were too slow for shows up as
     * an illegal step (counted), never as a wrong direction. */
    uint32_t pins = gpio_get_all();
    (void)events;
    if (gpio == BRIDGE_PIN_LEFT_A || gpio == BRIDGE_PIN_LEFT_B) {
        quad_update(&left_encoder, level(pins, BRIDGE_PIN_LEFT_A), level(pins, BRIDGE_PIN_LEFT_B));
    } else {
        quad_update(&right_encoder, level(pins, BRIDGE_PIN_RIGHT_A),
                    level(pins, BRIDGE_PIN_RIGHT_B));
    }
}

static void encoder_input(uint pin)
{
    gpio_init(pin);
    gpio_set_dir(pin, GPIO_IN);
    gpio_pull_up(pin); /* open-collector encoders; Schmitt trigger is on by default */
}

int main(void)
{
    static uint8_t buf[BRIDGE_MAX_WIRE];
    const bridge_config_t config = {
        BRIDGE_TICKS_PER_REV,
        BRIDGE_TICK_RATE_HZ,
        BRIDGE_HEARTBEAT_MS,
        (uint8_t)((BRIDGE_INVERT_LEFT ? BRIDGE_CONFIG_INVERT_LEFT : 0u) |
                  (BRIDGE_INVERT_RIGHT ? BRIDGE_CONFIG_INVERT_RIGHT : 0u)),
    };
    /* The RP2040 reports a brown-out as a power-on reset, so only the watchdog is told. */
    uint32_t sticky = watchdog_enable_caused_reboot() ? BRIDGE_FAULT_WATCHDOG_RESET : 0u;
    bridge_t bridge;
    bool was_connected = false;

    /* USB CDC through the SDK's stdio driver, but written with out_chars directly:
     * binary frames must not pass through stdio's CR/LF translation. */
    stdio_usb_init();

    encoder_input(BRIDGE_PIN_LEFT_A);
    encoder_input(BRIDGE_PIN_LEFT_B);
    encoder_input(BRIDGE_PIN_RIGHT_A);
    encoder_input(BRIDGE_PIN_RIGHT_B);
    quad_init(&left_encoder, gpio_get(BRIDGE_PIN_LEFT_A), gpio_get(BRIDGE_PIN_LEFT_B),
              BRIDGE_INVERT_LEFT);
    quad_init(&right_encoder, gpio_get(BRIDGE_PIN_RIGHT_A), gpio_get(BRIDGE_PIN_RIGHT_B),
              BRIDGE_INVERT_RIGHT);
    gpio_set_irq_enabled_with_callback(BRIDGE_PIN_LEFT_A, EDGES, true, &on_edge);
    gpio_set_irq_enabled(BRIDGE_PIN_LEFT_B, EDGES, true);
    gpio_set_irq_enabled(BRIDGE_PIN_RIGHT_A, EDGES, true);
    gpio_set_irq_enabled(BRIDGE_PIN_RIGHT_B, EDGES, true);

    bridge_init(&bridge, &config, (uint8_t)BRIDGE_BOARD_RP2040, (uint16_t)get_rand_32(), sticky);
    watchdog_enable(WATCHDOG_MS, true);

    for (;;) {
        bool connected = stdio_usb_connected(); /* DTR: a host has the port open */
        quad_t left;
        quad_t right;
        uint64_t now;
        uint32_t irq;
        size_t n;

        watchdog_update();
        if (connected && !was_connected) {
            bridge_request_config(&bridge); /* tell the new reader what we are */
        }
        was_connected = connected;
        if (time_us_64() < bridge_next_due(&bridge)) {
            continue;
        }
        /* Counts and time from one instant. */
        irq = save_and_disable_interrupts();
        left = left_encoder;
        right = right_encoder;
        now = time_us_64();
        restore_interrupts(irq);

        while ((n = bridge_poll(&bridge, now, &left, &right, buf, sizeof buf)) > 0) {
            /* Never block on a host that is not reading: drop and count instead. */
            if (connected && tud_cdc_write_available() >= n) {
                stdio_usb.out_chars((const char *)buf, (int)n);
            } else {
                bridge_frame_dropped(&bridge, connected);
            }
        }
    }
}
