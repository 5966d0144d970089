/*
 * 4x quadrature decoding: a state machine fed with the A/B pin levels.
 *
 * Portable C99: no OS, no malloc, no hardware access. The board layer calls
 * quad_update() from a pin-change interrupt (or a fast poll) with both levels;
 * the main loop copies the struct with interrupts masked to read it.
 *
 * Direction: "forward" (+1 per edge before inversion) is A leading B, i.e. the
 * pin pair (A, B) steps 00 -> 10 -> 11 -> 01 -> 00. A step where both pins
 * changed at once is illegal (a missed edge or noise): it adds no count and
 * increments `errors`.
 */
#ifndef TREETRAITS_QUADRATURE_H
#define TREETRAITS_QUADRATURE_H

#include <stdint.h>

typedef struct {
    uint32_t count;  /* cumulative count as int32 two's complement bits; wraps */
    uint32_t errors; /* cumulative illegal transitions; wraps */
    uint8_t state;   /* last levels: (A << 1) | B */
    uint8_t invert;  /* 1: forward counts down (the encoder is mounted mirrored) */
} quad_t;

/* Start counting from zero at the given pin levels (any non-zero level is high). */
void quad_init(quad_t *q, int a, int b, int invert);

/* Feed the current levels. Returns the step applied: -1, 0 or +1 (after inversion),
 * or 2 for an illegal transition. Calling it with unchanged levels is harmless. */
int quad_update(quad_t *q, int a, int b);

#endif
