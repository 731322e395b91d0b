/*
 * Car 3's brake ECU outside canbrake, in C on a SocketCAN raw socket (vcan0, can0).
 *
 * It follows docs/lockstep-protocol.md; the frame codec (canbrake.h / canbrake.c) is generated
 * from the run's DBC by `cantools generate_c_source` (see the Makefile). Control law: a PI speed
 * controller with feed-forward, F = m (a* + kp (v - v*) + ki * integral(v - v*)) N, + = brake.
 *
 * Per control period k:
 *   plant -> SYNC(k), REFERENCE, SENSOR_C3
 *   on SENSOR_C3: [HEARTBEAT_C3 every heartbeat period], STATE_C3, STATE_DONE_C3(k),
 *                 BRAKE_CMD_C3, CMD_DONE_C3(k)          (STATE_C3 and BRAKE_CMD_C3: E2E counter + CRC)
 * Before the first SYNC it sends HEARTBEAT_C3 every 100 ms (the run waits for it); it ends on
 * SYNC(0xFFFFFFFF). In realtime runs the two *_DONE barrier frames are not needed (--realtime).
 *
 *   ./build/foreign_ecu -c vcan0 --period-ms 2 [--realtime] [--mass-kg 19500] [--kp 36] [--ki 0]
 */
#include <errno.h>
#include <net/if.h>
#include <poll.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#include <linux/can.h>
#include <linux/can/raw.h>

#include "canbrake.h"

#define END_TICK 0xFFFFFFFFu
#define COUNTER_MODULO 15u   /* E2E alive counter = tick mod 15 (0..14) */
#define NMT_OPERATIONAL 5
#define NMT_PRE_OPERATIONAL 127

static int sock = -1;

/* CRC-8 SAE J1850 (poly 0x1D, init 0xFF, xor-out 0xFF) over the frame id (low byte, high byte)
 * and payload bytes 1..len-1; it goes into byte 0. */
static uint8_t crc8_step(uint8_t crc, uint8_t byte) {
    crc ^= byte;
    for (int i = 0; i < 8; i++)
        crc = (crc & 0x80) ? (uint8_t)((crc << 1) ^ 0x1D) : (uint8_t)(crc << 1);
    return crc;
}

static void e2e_protect(uint32_t frame_id, uint8_t *data, size_t len) {
    uint8_t crc = 0xFF;
    crc = crc8_step(crc, frame_id & 0xFF);
    crc = crc8_step(crc, (frame_id >> 8) & 0xFF);
    for (size_t i = 1; i < len; i++)
        crc = crc8_step(crc, data[i]);
    data[0] = crc ^ 0xFF;
}

static void send_frame(uint32_t id, const uint8_t *data, size_t len) {
    struct can_frame f;
    memset(&f, 0, sizeof f);
    f.can_id = id;
    f.can_dlc = (uint8_t)len;
    memcpy(f.data, data, len);
    for (int attempt = 0; attempt < 1000; attempt++) {  /* ENOBUFS: the interface queue is full */
        if (write(sock, &f, sizeof f) == (ssize_t)sizeof f)
            return;
        if (errno != ENOBUFS) {
            perror("write");
            exit(1);
        }
        usleep(100);
    }
    fprintf(stderr, "foreign_ecu: cannot send frame 0x%03x\n", (unsigned)id);
    exit(1);
}

static void send_heartbeat(uint8_t state) {
    struct canbrake_heartbeat_c3_t hb = {.node_state = state};
    uint8_t buf[8];
    int n = canbrake_heartbeat_c3_pack(buf, &hb, sizeof buf);
    send_frame(CANBRAKE_HEARTBEAT_C3_FRAME_ID, buf, (size_t)n);
}

static void send_done(uint32_t id, uint32_t tick) {
    /* STATE_DONE_C3 and CMD_DONE_C3 have the same layout: Tick, the low 16 bits of k */
    struct canbrake_cmd_done_c3_t d = {.tick = (uint16_t)(tick & 0xFFFF)};
    uint8_t buf[8];
    int n = canbrake_cmd_done_c3_pack(buf, &d, sizeof buf);
    send_frame(id, buf, (size_t)n);
}

static double now_s(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + ts.tv_nsec * 1e-9;
}

static void usage(FILE *out) {
    fprintf(out, "usage: foreign_ecu [-c CHANNEL] [--period-ms MS] [--realtime] [--mass-kg KG] [--kp K] "
                 "[--ki K] [--timeout-s S]\n"
                 "Car 3's brake ECU for a canbrake run (docs/lockstep-protocol.md).\n");
}

int main(int argc, char **argv) {
    const char *channel = "vcan0";
    double period_s = 0.002, mass_kg = 19500.0, kp = 36.0, ki = 0.0, timeout_s = 60.0;
    int realtime = 0;
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i];
        const char *v = i + 1 < argc ? argv[i + 1] : NULL;
        if (!strcmp(a, "-h") || !strcmp(a, "--help")) { usage(stdout); return 0; }
        else if (!strcmp(a, "--realtime")) realtime = 1;
        else if (v && (!strcmp(a, "-c") || !strcmp(a, "--channel"))) { channel = v; i++; }
        else if (v && !strcmp(a, "--period-ms")) { period_s = atof(v) / 1000.0; i++; }
        else if (v && !strcmp(a, "--mass-kg")) { mass_kg = atof(v); i++; }
        else if (v && !strcmp(a, "--kp")) { kp = atof(v); i++; }
        else if (v && !strcmp(a, "--ki")) { ki = atof(v); i++; }
        else if (v && !strcmp(a, "--timeout-s")) { timeout_s = atof(v); i++; }
        else { usage(stderr); return 2; }
    }
    if (period_s <= 0) { fprintf(stderr, "foreign_ecu: --period-ms must be > 0\n"); return 2; }
    uint32_t hb_every = (uint32_t)(0.1 / period_s + 0.5);   /* heartbeat every 100 ms of run time */
    if (hb_every == 0) hb_every = 1;

    /* a raw CAN socket on CHANNEL, receiving only SYNC, REFERENCE and our SENSOR frame */
    sock = socket(PF_CAN, SOCK_RAW, CAN_RAW);
    if (sock < 0) { perror("socket(PF_CAN)"); return 1; }
    struct ifreq ifr;
    memset(&ifr, 0, sizeof ifr);
    strncpy(ifr.ifr_name, channel, IFNAMSIZ - 1);
    if (ioctl(sock, SIOCGIFINDEX, &ifr) < 0) { fprintf(stderr, "foreign_ecu: no interface %s\n", channel); return 1; }
    struct can_filter rfilter[3] = {
        {CANBRAKE_SYNC_FRAME_ID, CAN_SFF_MASK | CAN_EFF_FLAG | CAN_RTR_FLAG},
        {CANBRAKE_REFERENCE_FRAME_ID, CAN_SFF_MASK | CAN_EFF_FLAG | CAN_RTR_FLAG},
        {CANBRAKE_SENSOR_C3_FRAME_ID, CAN_SFF_MASK | CAN_EFF_FLAG | CAN_RTR_FLAG},
    };
    setsockopt(sock, SOL_CAN_RAW, CAN_RAW_FILTER, rfilter, sizeof rfilter);
    struct sockaddr_can addr;
    memset(&addr, 0, sizeof addr);
    addr.can_family = AF_CAN;
    addr.can_ifindex = ifr.ifr_ifindex;
    if (bind(sock, (struct sockaddr *)&addr, sizeof addr) < 0) { perror("bind"); return 1; }

    int64_t k = -1;              /* tick of the newest SYNC; -1 before the run starts */
    double v_ref = 0.0, a_ref = 0.0, integral = 0.0;
    long answered = 0;
    double heard = now_s();
    struct pollfd pfd = {.fd = sock, .events = POLLIN};
    for (;;) {
        int r = poll(&pfd, 1, 100);
        if (r < 0 && errno != EINTR) { perror("poll"); return 1; }
        if (r <= 0) {
            if (k < 0) send_heartbeat(NMT_PRE_OPERATIONAL);  /* "I am here": the run starts on it */
            if (now_s() - heard > timeout_s) {
                fprintf(stderr, "foreign_ecu: no SYNC on %s for %g s\n", channel, timeout_s);
                return 1;
            }
            continue;
        }
        struct can_frame f;
        if (read(sock, &f, sizeof f) != (ssize_t)sizeof f) continue;
        heard = now_s();
        uint32_t id = f.can_id & CAN_SFF_MASK;
        if (id == CANBRAKE_SYNC_FRAME_ID) {
            struct canbrake_sync_t s;
            canbrake_sync_unpack(&s, f.data, f.can_dlc);
            if (s.tick == END_TICK) break;
            k = s.tick;
        } else if (id == CANBRAKE_REFERENCE_FRAME_ID) {
            struct canbrake_reference_t ref;
            canbrake_reference_unpack(&ref, f.data, f.can_dlc);
            v_ref = canbrake_reference_ref_speed_decode(ref.ref_speed);
            a_ref = canbrake_reference_ref_decel_decode(ref.ref_decel);
        } else if (id == CANBRAKE_SENSOR_C3_FRAME_ID && k >= 0) {
            struct canbrake_sensor_c3_t sen;
            canbrake_sensor_c3_unpack(&sen, f.data, f.can_dlc);
            double speed = canbrake_sensor_c3_speed_decode(sen.speed);
            double position = canbrake_sensor_c3_position_decode(sen.position);
            uint8_t counter = (uint8_t)(k % COUNTER_MODULO);
            uint8_t buf[8];
            int n;

            /* phase 1: heartbeat, our state for the ECUs that listen to us, the state barrier */
            if ((uint64_t)k % hb_every == 0) send_heartbeat(NMT_OPERATIONAL);
            struct canbrake_state_c3_t st = {
                .counter = counter,
                .speed = canbrake_state_c3_speed_encode(speed),
                .position = canbrake_state_c3_position_encode(position),
            };
            n = canbrake_state_c3_pack(buf, &st, sizeof buf);
            e2e_protect(CANBRAKE_STATE_C3_FRAME_ID, buf, (size_t)n);
            send_frame(CANBRAKE_STATE_C3_FRAME_ID, buf, (size_t)n);
            if (!realtime) send_done(CANBRAKE_STATE_DONE_C3_FRAME_ID, (uint32_t)k);

            /* phase 2: the control law, the command, the command barrier */
            double e = speed - v_ref;
            integral += e * period_s;
            double force_n = mass_kg * (a_ref + kp * e + ki * integral);
            struct canbrake_brake_cmd_c3_t cmd = {
                .counter = counter,
                .status = 0,
                .brake_force = canbrake_brake_cmd_c3_brake_force_encode(force_n),
            };
            n = canbrake_brake_cmd_c3_pack(buf, &cmd, sizeof buf);
            e2e_protect(CANBRAKE_BRAKE_CMD_C3_FRAME_ID, buf, (size_t)n);
            send_frame(CANBRAKE_BRAKE_CMD_C3_FRAME_ID, buf, (size_t)n);
            if (!realtime) send_done(CANBRAKE_CMD_DONE_C3_FRAME_ID, (uint32_t)k);
            answered++;
        }
    }
    close(sock);
    printf("C3: answered %ld control periods, the run ended\n", answered);
    return 0;
}
