/* 4x quadrature state machine: see quadrature.h. */
#include "quadrature.h"

#define QUAD_ILLEGAL 2

/* Indexed by (previous state << 2) | new state, with state = (A << 1) | B. */
static const int8_t QUAD_STEP[16] = {
    /*            new: 00            01            10            11 */
    /* old 00 */ 0,            -1,           +1,           QUAD_ILLEGAL,
    /* old 01 */ +1,           0,            QUAD_ILLEGAL, -1,
    /* old 10 */ -1,           QUAD_ILLEGAL, 0,            +1,
    /* old 11 */ QUAD_ILLEGAL, +1,           -1,           0,
};

static uint8_t quad_state(int a, int b)
{
    return (uint8_t)(((a != 0) << 1) | (b != 0));
}

void quad_init(quad_t *q, int a, int b, int invert)
{
    q->count = 0;
    q->errors = 0;
    q->state = quad_state(a, b);
    q->invert = (uint8_t)(invert != 0);
}

int quad_update(quad_t *q, int a, int b)
{
    uint8_t now = quad_state(a, b);
    int step = QUAD_STEP[(q->state << 2) | now];
    q->state = now;
    if (step == QUAD_ILLEGAL) {
        q->errors++;
        return QUAD_ILLEGAL;
    }
    if (q->invert) {
        step = -step;
    }
    /* Unsigned arithmetic: wrapping is defined, and the bits are the int32 count. */
    if (step > 0) {
        q->count++;
    } else if (step < 0) {
        q->count--;
    }
    return step;
}
