/*
 * bridge_sim: the portable core run on a host, for tests and bench work.
 *
 * Reads a script of pin levels from stdin (or --script FILE), one line per change:
 *
 *     T_US LEFT_A LEFT_B RIGHT_A RIGHT_B      # '#' starts a comment
 *
 * times in microseconds of board clock, non-decreasing, levels 0 or 1. The first line
 * gives the levels the decoders start from (no count); each later line feeds both
 * decoders. Frames are built by the same bridge_poll() a board runs, at the times they
 * fall due (or every --poll-us, to model a slow main loop), until --end-us (default:
 * the last line's time), and written to stdout or to --out PATH (a tty is put in raw
 * mode). A frame stamped T reflects every line at or before T. With --realtime the
 * frames are paced at the script's pace on the host's monotonic clock.
 *
 * Exit status: 0 done (or the link was closed under it), 2 bad arguments or script.
 */
#define _POSIX_C_SOURCE 200809L

#include <errno.h>
#include <fcntl.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "bridge.h"

typedef struct {
    uint64_t t_us;
    int pins[4];
} step_t;

static int out_fd = 1;
static int realtime = 0;
static struct timespec started;

static void usage(void)
{
    fprintf(stderr,
            "usage: bridge_sim [--script FILE] [--out PATH] [--realtime] [--end-us N]\n"
            "                  [--poll-us N] [--rate-hz N] [--heartbeat-ms N]\n"
            "                  [--ticks-per-rev N] [--invert-left] [--invert-right]\n"
            "                  [--reset-cause none|watchdog|brownout] [--boot-id N]\n");
}

static int parse_u64(const char *text, uint64_t *value)
{
    char *end;
    unsigned long long v;
    if (text == NULL || *text == '\0' || *text == '-') {
        return 0;
    }
    errno = 0;
    v = strtoull(text, &end, 10);
    if (errno != 0 || *end != '\0') {
        return 0;
    }
    *value = (uint64_t)v;
    return 1;
}

/* Parse one script line; returns 1 for a step, 0 for a blank/comment line, -1 bad. */
static int parse_line(char *line, step_t *step)
{
    char *hash = strchr(line, '#');
    char *field;
    char *save = NULL;
    int i;
    if (hash != NULL) {
        *hash = '\0';
    }
    field = strtok_r(line, " \t\r\n", &save);
    if (field == NULL) {
        return 0;
    }
    if (!parse_u64(field, &step->t_us)) {
        return -1;
    }
    for (i = 0; i < 4; i++) {
        field = strtok_r(NULL, " \t\r\n", &save);
        if (field == NULL || (strcmp(field, "0") != 0 && strcmp(field, "1") != 0)) {
            return -1;
        }
        step->pins[i] = field[0] == '1';
    }
    return strtok_r(NULL, " \t\r\n", &save) == NULL ? 1 : -1;
}

static void pace(uint64_t t_us)
{
    struct timespec now;
    uint64_t elapsed_us;
    if (!realtime) {
        return;
    }
    clock_gettime(CLOCK_MONOTONIC, &now);
    elapsed_us = (uint64_t)(now.tv_sec - started.tv_sec) * 1000000u +
                 (uint64_t)((now.tv_nsec - started.tv_nsec) / 1000);
    if (t_us > elapsed_us) {
        uint64_t wait = t_us - elapsed_us;
        struct timespec ts;
        ts.tv_sec = (time_t)(wait / 1000000u);
        ts.tv_nsec = (long)(wait % 1000000u) * 1000L;
        while (nanosleep(&ts, &ts) != 0 && errno == EINTR) {
        }
    }
}

/* Returns 0 when the link is gone (the host closed the pty or the pipe). */
static int send_all(const uint8_t *buf, size_t len)
{
    while (len > 0) {
        ssize_t n = write(out_fd, buf, len);
        if (n < 0) {
            if (errno == EINTR) {
                continue;
            }
            return 0;
        }
        buf += n;
        len -= (size_t)n;
    }
    return 1;
}

static int poll_at(bridge_t *b, uint64_t t_us, const quad_t *left, const quad_t *right)
{
    uint8_t buf[BRIDGE_MAX_WIRE];
    size_t n;
    pace(t_us);
    while ((n = bridge_poll(b, t_us, left, right, buf, sizeof buf)) > 0) {
        if (!send_all(buf, n)) {
            return 0;
        }
    }
    return 1;
}

static int open_out(const char *path)
{
    struct termios tio;
    int fd = open(path, O_WRONLY | O_NOCTTY);
    if (fd < 0) {
        fprintf(stderr, "bridge_sim: cannot open %s: %s\n", path, strerror(errno));
        return -1;
    }
    if (isatty(fd) && tcgetattr(fd, &tio) == 0) {
        /* Raw: the frames are binary, no CR/LF translation. */
        tio.c_iflag &= ~(tcflag_t)(IGNBRK | BRKINT | PARMRK | ISTRIP | INLCR | IGNCR | ICRNL |
                                   IXON);
        tio.c_oflag &= ~(tcflag_t)OPOST;
        tio.c_lflag &= ~(tcflag_t)(ECHO | ECHONL | ICANON | ISIG | IEXTEN);
        tio.c_cflag &= ~(tcflag_t)(CSIZE | PARENB);
        tio.c_cflag |= CS8;
        tcsetattr(fd, TCSANOW, &tio);
    }
    return fd;
}

int main(int argc, char **argv)
{
    const char *script_path = NULL;
    const char *out_path = NULL;
    uint64_t end_us = 0;
    int have_end = 0;
    uint64_t poll_us = 0;
    uint64_t value;
    uint32_t sticky = 0;
    uint16_t boot_id = 0;
    bridge_config_t config = {4096u, 100u, 1000u, 0u};
    FILE *script = stdin;
    char line[256];
    step_t step;
    quad_t left;
    quad_t right;
    bridge_t b;
    uint64_t poll_t;
    uint64_t last_t = 0;
    int have_init = 0;
    int lineno = 0;
    int i;

    for (i = 1; i < argc; i++) {
        const char *arg = argv[i];
        const char *next = i + 1 < argc ? argv[i + 1] : NULL;
        if (strcmp(arg, "--realtime") == 0) {
            realtime = 1;
        } else if (strcmp(arg, "--invert-left") == 0) {
            config.flags |= BRIDGE_CONFIG_INVERT_LEFT;
        } else if (strcmp(arg, "--invert-right") == 0) {
            config.flags |= BRIDGE_CONFIG_INVERT_RIGHT;
        } else if (next == NULL) {
            usage();
            return 2;
        } else if (strcmp(arg, "--script") == 0) {
            script_path = argv[++i];
        } else if (strcmp(arg, "--out") == 0) {
            out_path = argv[++i];
        } else if (strcmp(arg, "--reset-cause") == 0) {
            i++;
            if (strcmp(next, "watchdog") == 0) {
                sticky = BRIDGE_FAULT_WATCHDOG_RESET;
            } else if (strcmp(next, "brownout") == 0) {
                sticky = BRIDGE_FAULT_BROWNOUT_RESET;
            } else if (strcmp(next, "none") != 0) {
                usage();
                return 2;
            }
        } else if (parse_u64(next, &value)) {
            i++;
            if (strcmp(arg, "--end-us") == 0) {
                end_us = value;
                have_end = 1;
            } else if (strcmp(arg, "--boot-id") == 0 && value <= 0xFFFFu) {
                boot_id = (uint16_t)value;
            } else if (strcmp(arg, "--poll-us") == 0) {
                poll_us = value;
            } else if (strcmp(arg, "--rate-hz") == 0 && value >= 1 && value <= 1000) {
                config.tick_rate_hz = (uint16_t)value;
            } else if (strcmp(arg, "--heartbeat-ms") == 0 && value >= 1 && value <= 60000) {
                config.heartbeat_period_ms = (uint16_t)value;
            } else if (strcmp(arg, "--ticks-per-rev") == 0 && value >= 1 &&
                       value <= 0xFFFFFFFFu) {
                config.ticks_per_rev = (uint32_t)value;
            } else {
                usage();
                return 2;
            }
        } else {
            usage();
            return 2;
        }
    }

    if (script_path != NULL && (script = fopen(script_path, "r")) == NULL) {
        fprintf(stderr, "bridge_sim: cannot open %s: %s\n", script_path, strerror(errno));
        return 2;
    }
    if (out_path != NULL && (out_fd = open_out(out_path)) < 0) {
        return 2;
    }
    signal(SIGPIPE, SIG_IGN); /* a closed reader shows up as a failed write */
    clock_gettime(CLOCK_MONOTONIC, &started);

    bridge_init(&b, &config, (uint8_t)BRIDGE_BOARD_HOST_SIM, boot_id, sticky);
    quad_init(&left, 0, 0, config.flags & BRIDGE_CONFIG_INVERT_LEFT);
    quad_init(&right, 0, 0, config.flags & BRIDGE_CONFIG_INVERT_RIGHT);
    poll_t = 0;

    while (fgets(line, sizeof line, script) != NULL) {
        int kind;
        lineno++;
        kind = parse_line(line, &step);
        if (kind == 0) {
            continue;
        }
        if (kind < 0 || (have_init && step.t_us < last_t)) {
            fprintf(stderr,
                    "bridge_sim: script line %d: expected 'T_US LA LB RA RB' with levels 0/1 "
                    "and non-decreasing times\n",
                    lineno);
            return 2;
        }
        last_t = step.t_us;
        if (!have_init) {
            have_init = 1;
            quad_init(&left, step.pins[0], step.pins[1], config.flags & BRIDGE_CONFIG_INVERT_LEFT);
            quad_init(&right, step.pins[2], step.pins[3],
                      config.flags & BRIDGE_CONFIG_INVERT_RIGHT);
            continue;
        }
        while (poll_t < step.t_us && (!have_end || poll_t <= end_us)) {
            if (!poll_at(&b, poll_t, &left, &right)) {
                return 0;
            }
            poll_t = poll_us ? poll_t + poll_us : bridge_next_due(&b);
        }
        quad_update(&left, step.pins[0], step.pins[1]);
        quad_update(&right, step.pins[2], step.pins[3]);
    }
    if (!have_end) {
        end_us = last_t;
    }
    while (poll_t <= end_us) {
        if (!poll_at(&b, poll_t, &left, &right)) {
            return 0;
        }
        poll_t = poll_us ? poll_t + poll_us : bridge_next_due(&b);
    }
    return 0;
}
