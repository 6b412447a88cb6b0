/* SPDX-License-Identifier: Apache-2.0 */
/*
 * magcal-sil: the firmware's protocol endpoint (device.h) as a native process, the
 * software-in-the-loop device the host tool and the tests talk to.
 *
 *   magcal-sil --flash PATH [--pty | --tcp PORT] [--feed-tcp PORT] [--uid HEX]
 *
 *   --flash PATH     the parameter flash, a file (flash_file.h: 2 pages of SIL_FLASH_PAGE_SIZE
 *                    bytes, slot A page 0, slot B page 1); created erased when missing, so a
 *                    committed set survives a restart of the process.
 *   --pty            (default) serve the protocol on a pseudo-terminal in raw mode.
 *   --tcp PORT       serve it on 127.0.0.1:PORT instead (0: an ephemeral port). One client at
 *                    a time; further clients wait in the backlog until it disconnects.
 *   --feed-tcp PORT  the sensor feed on 127.0.0.1:PORT (default 0: ephemeral), one client,
 *                    lines in sensor_feed.h's format. Each S line (raw counts) or P line
 *                    (physical values, which the feed quantises with the sensors' count
 *                    scales below, as their ADCs would) is one acquired sample (then
 *                    streamed as the running stream says), an E line a failed read, a T line
 *                    only moves the clock. A line the feed refuses is reported on stderr
 *                    ("magcal-sil: feed line N: status S (why), skipped: LINE") and skipped;
 *                    the device goes on.
 *   --uid HEX        the 96-bit device uid, 1 to 24 hex digits (optional 0x); info's
 *                    device_uid[0] is its least significant 32 bits. Default 0 (none).
 *
 * On start it prints, each line flushed:
 *   magcal-sil: protocol pty /dev/pts/N        (or: magcal-sil: protocol tcp 127.0.0.1:PORT)
 *   magcal-sil: feed tcp 127.0.0.1:PORT
 *   magcal-sil: ready
 * and nothing more on stdout. SIGINT and SIGTERM exit with status 0; every error prints one
 * line on stderr and exits with status 1 (2 for a usage error).
 *
 * The SIL's sensors (info), datasheet values as count scales of sensor_hal.h:
 *   magnetometer   LIS3MDL (WHO_AM_I 0x3D) at +-4 gauss, 6842 LSB/gauss:
 *                  count {1, 6842, 0, GAUSS}, full scale {4, 1, 0, GAUSS};
 *   accelerometer  LSM6DSO (WHO_AM_I 0x6C) at +-4 g, 0.122 mg/LSB:
 *                  count {122, 1, -6, STANDARD_GRAVITY}, full scale {4, 1, 0, STANDARD_GRAVITY};
 *   gyroscope      LSM6DSO at +-500 dps, 17.5 mdps/LSB:
 *                  count {175, 1, -4, DEG_PER_S}, full scale {500, 1, 0, DEG_PER_S};
 *   nominal rate   100 Hz (sample_rate_mhz 100000); the feed drives the real timing.
 *
 * I/O: one poll() over the signal self-pipe, the protocol fd (pty master or TCP client, or
 * the listening socket while no client is connected) and the feed socket (likewise). Writes
 * are non-blocking through a bounded transmit queue (SIL_TXQ_SIZE bytes): the device's tx
 * takes what fits, so when the link is slow stream messages are dropped and counted by the
 * device, and a response that does not fit stays pending in the device, which then stops
 * reading requests until it is out (device.h). With no TCP client, tx takes nothing. A TCP
 * client's kernel send buffer is limited (SIL_SOCK_SNDBUF) so the link fills like a serial
 * line's buffers do, in hundreds of messages rather than megabytes.
 *
 * reset (the protocol request) resets the device state in-process (device.h: no stream, no
 * staged set, an empty retry cache, the active set re-read from the flash file); the pty or
 * port stays the same, like a reboot of a board on the same cable.
 */
#define _XOPEN_SOURCE 700

#include <errno.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <termios.h>
#include <unistd.h>
#include <arpa/inet.h>

#include "../demo_sensors.h"
#include "flash_file.h"
#include "magcal/device.h"
#include "sensor_feed.h"

#ifndef MC_SIL_FW_BUILD
#define MC_SIL_FW_BUILD 0u
#endif
#define SIL_FW_MAJOR 0u
#define SIL_FW_MINOR 1u
#define SIL_FW_PATCH 0u

#define SIL_FLASH_PAGE_SIZE 2048u
#define SIL_FLASH_PAGES 2u
#define SIL_SAMPLE_RATE_MHZ 100000u
#define SIL_TXQ_SIZE 16384u
/* The TCP client socket's kernel send buffer: without a limit Linux lets megabytes of stream
 * queue up on loopback, so a slow host would see stale samples instead of counted drops. */
#define SIL_SOCK_SNDBUF 16384u
#define SIL_RX_SIZE 4096u
/* A P line of nine 24-character reprs ("-1.2345678901234567e-05") is about 250 bytes. */
#define SIL_FEED_LINE_MAX 512u

typedef struct {
    uint8_t buf[SIL_TXQ_SIZE];
    size_t head; /* index of the oldest byte */
    size_t len;
} txq_t;

typedef struct {
    int is_pty;
    int proto_listen; /* TCP listening socket, -1 for a pty */
    int proto_fd;     /* pty master or TCP client, -1 when none */
    int pty_slave;    /* kept open so the master never sees a hang-up */
    int feed_listen;
    int feed_fd;
    int sig_pipe[2];
    uint8_t rx[SIL_RX_SIZE]; /* protocol input the device has not used yet */
    size_t rx_len;
    char line[SIL_FEED_LINE_MAX + 1u];
    size_t line_len;
    int line_overlong;
    unsigned long line_no;
    txq_t txq;
    mc_flash_file_t ff;
    mc_sensor_feed_t feed;
    mc_sensor_hal_t hal;
    mc_sample_t ring[MC_RING_CAPACITY];
    mc_device_t dev;
} sil_t;

static sil_t S;

static void fail(const char *what)
{
    if (errno != 0) {
        fprintf(stderr, "magcal-sil: %s: %s\n", what, strerror(errno));
    } else {
        fprintf(stderr, "magcal-sil: %s\n", what);
    }
    exit(1);
}

static void usage(const char *what)
{
    fprintf(stderr,
            "magcal-sil: %s (usage: magcal-sil --flash PATH [--pty | --tcp PORT] "
            "[--feed-tcp PORT] [--uid HEX])\n",
            what);
    exit(2);
}

/* ---------------------------------------------------------------- signals */

static void on_signal(int sig)
{
    const int saved = errno;
    const uint8_t b = (uint8_t)sig;
    (void)!write(S.sig_pipe[1], &b, 1u);
    errno = saved;
}

static int set_nonblock(int fd)
{
    const int fl = fcntl(fd, F_GETFL);
    return fl < 0 ? -1 : fcntl(fd, F_SETFL, fl | O_NONBLOCK);
}

static void setup_signals(void)
{
    struct sigaction sa;
    if (pipe(S.sig_pipe) != 0 || set_nonblock(S.sig_pipe[0]) != 0 ||
        set_nonblock(S.sig_pipe[1]) != 0) {
        fail("signal pipe");
    }
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigemptyset(&sa.sa_mask);
    if (sigaction(SIGINT, &sa, NULL) != 0 || sigaction(SIGTERM, &sa, NULL) != 0) {
        fail("sigaction");
    }
    sa.sa_handler = SIG_IGN;
    if (sigaction(SIGPIPE, &sa, NULL) != 0) {
        fail("sigaction");
    }
}

/* ---------------------------------------------------------------- arguments */

static int parse_port(const char *s, unsigned *port)
{
    char *end = NULL;
    unsigned long v;
    if (s == NULL || *s < '0' || *s > '9') {
        return -1;
    }
    errno = 0;
    v = strtoul(s, &end, 10);
    if (errno != 0 || *end != '\0' || v > 65535ul) {
        return -1;
    }
    *port = (unsigned)v;
    return 0;
}

static int parse_uid(const char *s, uint32_t uid[3])
{
    size_t n;
    if (s == NULL) {
        return -1;
    }
    if (s[0] == '0' && (s[1] == 'x' || s[1] == 'X')) {
        s += 2;
    }
    n = strlen(s);
    if (n == 0u || n > 24u) {
        return -1;
    }
    uid[0] = uid[1] = uid[2] = 0u;
    for (size_t i = 0; i < n; ++i) {
        const char c = s[i];
        uint32_t d;
        if (c >= '0' && c <= '9') {
            d = (uint32_t)(c - '0');
        } else if (c >= 'a' && c <= 'f') {
            d = (uint32_t)(c - 'a' + 10);
        } else if (c >= 'A' && c <= 'F') {
            d = (uint32_t)(c - 'A' + 10);
        } else {
            return -1;
        }
        /* shift the 96-bit number left by 4 and add d */
        uid[2] = (uid[2] << 4) | (uid[1] >> 28);
        uid[1] = (uid[1] << 4) | (uid[0] >> 28);
        uid[0] = (uid[0] << 4) | d;
    }
    return 0;
}

/* ---------------------------------------------------------------- channels */

static int listen_tcp(unsigned port, unsigned *bound)
{
    struct sockaddr_in a;
    socklen_t alen = sizeof a;
    const int one = 1;
    const int fd = socket(AF_INET, SOCK_STREAM, 0);
    if (fd < 0) {
        return -1;
    }
    memset(&a, 0, sizeof a);
    a.sin_family = AF_INET;
    a.sin_port = htons((uint16_t)port);
    a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    if (setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one) != 0 ||
        bind(fd, (struct sockaddr *)&a, sizeof a) != 0 || listen(fd, 4) != 0 ||
        set_nonblock(fd) != 0 || getsockname(fd, (struct sockaddr *)&a, &alen) != 0) {
        const int saved = errno;
        close(fd);
        errno = saved;
        return -1;
    }
    *bound = ntohs(a.sin_port);
    return fd;
}

static const char *open_pty(void)
{
    struct termios t;
    const char *name;
    S.proto_fd = posix_openpt(O_RDWR | O_NOCTTY);
    if (S.proto_fd < 0 || grantpt(S.proto_fd) != 0 || unlockpt(S.proto_fd) != 0) {
        fail("pseudo-terminal");
    }
    name = ptsname(S.proto_fd);
    if (name == NULL) {
        fail("ptsname");
    }
    S.pty_slave = open(name, O_RDWR | O_NOCTTY);
    if (S.pty_slave < 0 || tcgetattr(S.pty_slave, &t) != 0) {
        fail("pseudo-terminal slave");
    }
    /* raw mode, as cfmakeraw does */
    t.c_iflag &= ~(tcflag_t)(IGNBRK | BRKINT | PARMRK | ISTRIP | INLCR | IGNCR | ICRNL | IXON);
    t.c_oflag &= ~(tcflag_t)OPOST;
    t.c_lflag &= ~(tcflag_t)(ECHO | ECHONL | ICANON | ISIG | IEXTEN);
    t.c_cflag &= ~(tcflag_t)(CSIZE | PARENB);
    t.c_cflag |= CS8;
    t.c_cc[VMIN] = 1;
    t.c_cc[VTIME] = 0;
    if (tcsetattr(S.pty_slave, TCSANOW, &t) != 0 || set_nonblock(S.proto_fd) != 0) {
        fail("pseudo-terminal raw mode");
    }
    return name;
}

/* ---------------------------------------------------------------- transmit queue */

static int sil_tx(void *ctx, const uint8_t *bytes, size_t len)
{
    txq_t *q = (txq_t *)ctx;
    size_t take;
    if (S.proto_fd < 0) {
        return 0; /* no client: nothing reaches a link */
    }
    take = SIL_TXQ_SIZE - q->len;
    if (take > len) {
        take = len;
    }
    for (size_t i = 0; i < take; ++i) {
        q->buf[(q->head + q->len + i) % SIL_TXQ_SIZE] = bytes[i];
    }
    q->len += take;
    return (int)take;
}

static void drop_client(void)
{
    if (S.proto_fd >= 0 && !S.is_pty) {
        close(S.proto_fd);
        S.proto_fd = -1;
    }
    S.rx_len = 0u;
    S.txq.head = 0u;
    S.txq.len = 0u;
    (void)mc_device_link_reset(&S.dev);
}

/* Writes what the link takes now. */
static void flush_txq(void)
{
    while (S.proto_fd >= 0 && S.txq.len > 0u) {
        size_t chunk = SIL_TXQ_SIZE - S.txq.head;
        ssize_t n;
        if (chunk > S.txq.len) {
            chunk = S.txq.len;
        }
        if (S.is_pty) {
            n = write(S.proto_fd, &S.txq.buf[S.txq.head], chunk);
        } else {
            n = send(S.proto_fd, &S.txq.buf[S.txq.head], chunk, MSG_NOSIGNAL);
        }
        if (n < 0 && errno == EINTR) {
            continue;
        }
        if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK)) {
            return;
        }
        if (n <= 0) {
            if (S.is_pty) {
                fail("write to the pseudo-terminal");
            }
            drop_client(); /* the client went away */
            return;
        }
        S.txq.head = (S.txq.head + (size_t)n) % SIL_TXQ_SIZE;
        S.txq.len -= (size_t)n;
    }
}

/* Lets the device send what it holds, then use the input it has not used yet. */
static void pump(void)
{
    size_t used;
    flush_txq();
    (void)mc_device_poll(&S.dev);
    flush_txq();
    if (S.rx_len > 0u) {
        used = mc_device_rx_bytes(&S.dev, S.rx, S.rx_len);
        memmove(S.rx, S.rx + used, S.rx_len - used);
        S.rx_len -= used;
        flush_txq();
    }
}

/* ---------------------------------------------------------------- feed */

static void feed_line(void)
{
    mc_status_t st;
    S.line[S.line_len] = '\0';
    ++S.line_no;
    if (S.line_overlong) {
        fprintf(stderr, "magcal-sil: feed line %lu: longer than %u bytes, skipped\n", S.line_no,
                SIL_FEED_LINE_MAX);
        return;
    }
    if (S.line_len == 0u || (S.line_len == 1u && S.line[0] == '\r')) {
        return; /* blank line */
    }
    st = mc_sensor_feed_apply_line(&S.feed, S.line);
    if (st != MC_OK) {
        if (S.line_len > 0u && S.line[S.line_len - 1u] == '\r') {
            S.line[S.line_len - 1u] = '\0';
        }
        fprintf(stderr, "magcal-sil: feed line %lu: status %d (%s), skipped: %s\n", S.line_no,
                (int)st, mc_sensor_feed_refusal(st), S.line);
        return;
    }
    if (mc_sensor_feed_pending(&S.feed)) {
        (void)mc_device_sample(&S.dev);
        pump();
    }
}

static void feed_bytes(const char *data, size_t n)
{
    for (size_t i = 0; i < n; ++i) {
        if (data[i] == '\n') {
            feed_line();
            S.line_len = 0u;
            S.line_overlong = 0;
        } else if (S.line_len < SIL_FEED_LINE_MAX) {
            S.line[S.line_len++] = data[i];
        } else {
            S.line_overlong = 1;
        }
    }
}

static void close_feed(void)
{
    close(S.feed_fd);
    S.feed_fd = -1;
    S.line_len = 0u;
    S.line_overlong = 0;
}

/* ---------------------------------------------------------------- device */

static void init_device(const uint32_t uid[3])
{
    mc_sensor_info_t info[MC_SENSOR_COUNT];
    mc_device_config_t cfg;

    mc_demo_sensors_describe(info);
    errno = 0;
    if (mc_sensor_feed_init(&S.feed, info) != MC_OK) {
        fail("sensor feed: invalid sensor description");
    }
    S.hal = mc_sensor_feed_hal(&S.feed);

    memset(&cfg, 0, sizeof cfg);
    cfg.tx = sil_tx;
    cfg.tx_ctx = &S.txq;
    cfg.hal = &S.hal;
    cfg.ring = S.ring;
    cfg.ring_capacity = MC_RING_CAPACITY;
    cfg.flash = &S.ff.flash;
    cfg.slot_a_page = 0u;
    cfg.slot_b_page = 1u;
    cfg.pages_per_slot = 1u;
    cfg.fw_version[0] = SIL_FW_MAJOR;
    cfg.fw_version[1] = SIL_FW_MINOR;
    cfg.fw_version[2] = SIL_FW_PATCH;
    cfg.fw_build = (uint32_t)(MC_SIL_FW_BUILD);
    memcpy(cfg.device_uid, uid, sizeof cfg.device_uid);
    cfg.sample_rate_mhz = SIL_SAMPLE_RATE_MHZ;
    if (mc_device_init(&S.dev, &cfg) != MC_OK) {
        fail("device init");
    }
}

/* ---------------------------------------------------------------- main loop */

enum { FD_SIG, FD_PROTO, FD_FEED, FD_COUNT };

static void accept_proto(void)
{
    const int one = 1;
    const int sndbuf = (int)SIL_SOCK_SNDBUF;
    const int fd = accept(S.proto_listen, NULL, NULL);
    if (fd < 0) {
        if (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR ||
            errno == ECONNABORTED) {
            return;
        }
        fail("accept (protocol)");
    }
    if (set_nonblock(fd) != 0) {
        fail("protocol client");
    }
    (void)setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
    (void)setsockopt(fd, SOL_SOCKET, SO_SNDBUF, &sndbuf, sizeof sndbuf);
    drop_client();
    S.proto_fd = fd;
}

static void read_proto(void)
{
    const ssize_t n = read(S.proto_fd, S.rx + S.rx_len, SIL_RX_SIZE - S.rx_len);
    if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR)) {
        return;
    }
    if (n <= 0) {
        if (S.is_pty) {
            if (n < 0 && errno == EIO) {
                return; /* not while we hold the slave; harmless if it happens */
            }
            fail("read from the pseudo-terminal");
        }
        drop_client();
        return;
    }
    S.rx_len += (size_t)n;
}

static void accept_feed(void)
{
    const int fd = accept(S.feed_listen, NULL, NULL);
    if (fd < 0) {
        if (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR ||
            errno == ECONNABORTED) {
            return;
        }
        fail("accept (feed)");
    }
    if (set_nonblock(fd) != 0) {
        fail("feed client");
    }
    S.feed_fd = fd;
    S.line_len = 0u;
    S.line_overlong = 0;
}

static void read_feed(void)
{
    char buf[4096];
    const ssize_t n = read(S.feed_fd, buf, sizeof buf);
    if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR)) {
        return;
    }
    if (n <= 0) {
        close_feed();
        return;
    }
    feed_bytes(buf, (size_t)n);
}

static void run(void)
{
    struct pollfd fds[FD_COUNT];
    for (;;) {
        int busy;
        memset(fds, 0, sizeof fds);
        fds[FD_SIG].fd = S.sig_pipe[0];
        fds[FD_SIG].events = POLLIN;
        busy = S.txq.len > 0u || mc_device_tx_pending(&S.dev);
        if (S.proto_fd >= 0) {
            fds[FD_PROTO].fd = S.proto_fd;
            fds[FD_PROTO].events = (short)((S.rx_len < SIL_RX_SIZE ? POLLIN : 0) |
                                           (busy ? POLLOUT : 0));
        } else {
            fds[FD_PROTO].fd = S.proto_listen;
            fds[FD_PROTO].events = POLLIN;
        }
        fds[FD_FEED].fd = S.feed_fd >= 0 ? S.feed_fd : S.feed_listen;
        fds[FD_FEED].events = POLLIN;
        if (poll(fds, FD_COUNT, -1) < 0) {
            if (errno == EINTR) {
                continue;
            }
            fail("poll");
        }
        if (fds[FD_SIG].revents != 0) {
            return;
        }
        if (fds[FD_PROTO].revents != 0) {
            if (S.proto_fd < 0) {
                accept_proto();
            } else if (fds[FD_PROTO].revents & (POLLIN | POLLHUP | POLLERR)) {
                read_proto();
            }
        }
        if (fds[FD_FEED].revents != 0) {
            if (S.feed_fd < 0) {
                accept_feed();
            } else {
                read_feed();
            }
        }
        pump();
    }
}

int main(int argc, char **argv)
{
    const char *flash_path = NULL;
    unsigned proto_port = 0u, feed_port = 0u, bound = 0u;
    uint32_t uid[3] = {0u, 0u, 0u};
    mc_status_t st;

    memset(&S, 0, sizeof S);
    S.is_pty = 1;
    S.proto_listen = S.proto_fd = S.pty_slave = S.feed_listen = S.feed_fd = -1;
    for (int i = 1; i < argc; ++i) {
        const char *a = argv[i];
        const char *v = i + 1 < argc ? argv[i + 1] : NULL;
        if (strcmp(a, "--flash") == 0 && v != NULL) {
            flash_path = v;
            ++i;
        } else if (strcmp(a, "--pty") == 0) {
            S.is_pty = 1;
        } else if (strcmp(a, "--tcp") == 0) {
            if (parse_port(v, &proto_port) != 0) {
                usage("--tcp needs a port number 0..65535");
            }
            S.is_pty = 0;
            ++i;
        } else if (strcmp(a, "--feed-tcp") == 0) {
            if (parse_port(v, &feed_port) != 0) {
                usage("--feed-tcp needs a port number 0..65535");
            }
            ++i;
        } else if (strcmp(a, "--uid") == 0) {
            if (parse_uid(v, uid) != 0) {
                usage("--uid needs 1 to 24 hex digits");
            }
            ++i;
        } else {
            char msg[160];
            snprintf(msg, sizeof msg, "unknown or incomplete argument '%.100s'", a);
            usage(msg);
        }
    }
    if (flash_path == NULL) {
        usage("--flash PATH is required");
    }
    setup_signals();

    errno = 0;
    st = mc_flash_file_open(&S.ff, flash_path, SIL_FLASH_PAGE_SIZE, SIL_FLASH_PAGES);
    if (st != MC_OK) {
        fprintf(stderr, "magcal-sil: flash file %s: status %d (%s)\n", flash_path, (int)st,
                st == MC_E_RANGE ? "a file of another size" : "cannot open or create it");
        return 1;
    }
    init_device(uid);

    if (S.is_pty) {
        const char *name = open_pty();
        printf("magcal-sil: protocol pty %s\n", name);
    } else {
        S.proto_listen = listen_tcp(proto_port, &bound);
        if (S.proto_listen < 0) {
            fail("protocol socket on 127.0.0.1");
        }
        printf("magcal-sil: protocol tcp 127.0.0.1:%u\n", bound);
    }
    fflush(stdout);
    S.feed_listen = listen_tcp(feed_port, &bound);
    if (S.feed_listen < 0) {
        fail("feed socket on 127.0.0.1");
    }
    printf("magcal-sil: feed tcp 127.0.0.1:%u\n", bound);
    fflush(stdout);
    printf("magcal-sil: ready\n");
    fflush(stdout);

    run();

    if (mc_flash_file_close(&S.ff) != MC_OK) {
        errno = 0;
        fail("closing the flash file");
    }
    return 0;
}
