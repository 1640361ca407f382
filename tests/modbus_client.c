/* An independent Modbus TCP client for the tests of plcstack's Modbus server: libmodbus.
 *
 *   modbus_client HOST PORT UNIT CMD [CMD ...]
 *
 * Each CMD is one request; one line of output per request, in order:
 *   rc ADDR N        FC 1  read coils               -> "ok 1 0 1 ..."
 *   rd ADDR N        FC 2  read discrete inputs
 *   rh ADDR N        FC 3  read holding registers   -> "ok 1234 65535 ..."
 *   ri ADDR N        FC 4  read input registers
 *   wc ADDR V        FC 5  write single coil (V 0 or 1)     -> "ok"
 *   wh ADDR V        FC 6  write single register
 *   wcs ADDR N V...  FC 15 write multiple coils
 *   whs ADDR N V...  FC 16 write multiple registers
 * A Modbus exception answer prints "exc 0xNN", any other failure "err TEXT".
 *
 *   modbus_client HOST PORT UNIT bench SECONDS HZ ADDR N
 * reads N holding registers from ADDR at HZ for SECONDS and prints one response time in
 * microseconds per line (then "failures F"), for the benchmark.
 */
#include <errno.h>
#include <modbus.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

static void report_error(void) {
    if (errno > MODBUS_ENOBASE && errno <= MODBUS_ENOBASE + 11)
        printf("exc 0x%02X\n", errno - MODBUS_ENOBASE);
    else
        printf("err %s\n", modbus_strerror(errno));
}

static double now(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec + ts.tv_nsec / 1e9;
}

static int bench(modbus_t *ctx, double seconds, double hz, int addr, int n) {
    uint16_t regs[125];
    double start = now(), next = start;
    int failures = 0;
    while (next < start + seconds) {
        double t0 = now();
        if (t0 < next) {
            struct timespec ts = {0, (long)((next - t0) * 1e9)};
            nanosleep(&ts, NULL);
            t0 = now();
        }
        if (modbus_read_registers(ctx, addr, n, regs) != n)
            failures++;
        else
            printf("%ld\n", (long)((now() - t0) * 1e6));
        next += 1.0 / hz;
    }
    printf("failures %d\n", failures);
    return 0;
}

int main(int argc, char **argv) {
    if (argc < 5) {
        fprintf(stderr, "usage: %s HOST PORT UNIT CMD...\n", argv[0]);
        return 2;
    }
    modbus_t *ctx = modbus_new_tcp(argv[1], atoi(argv[2]));
    if (ctx == NULL || modbus_set_slave(ctx, atoi(argv[3])) != 0) {
        fprintf(stderr, "modbus context: %s\n", modbus_strerror(errno));
        return 1;
    }
    modbus_set_response_timeout(ctx, 10, 0);
    if (modbus_connect(ctx) != 0) {
        fprintf(stderr, "connect: %s\n", modbus_strerror(errno));
        return 1;
    }
    int i = 4;
    if (strcmp(argv[i], "bench") == 0 && argc == 9) {
        int rc = bench(ctx, atof(argv[5]), atof(argv[6]), atoi(argv[7]), atoi(argv[8]));
        modbus_close(ctx);
        modbus_free(ctx);
        return rc;
    }
    while (i + 2 < argc) {
        const char *cmd = argv[i];
        int addr = atoi(argv[i + 1]);
        int n = atoi(argv[i + 2]);
        i += 3;
        if (strcmp(cmd, "rc") == 0 || strcmp(cmd, "rd") == 0) {
            uint8_t bits[2000];
            int rc = cmd[1] == 'c' ? modbus_read_bits(ctx, addr, n, bits)
                                   : modbus_read_input_bits(ctx, addr, n, bits);
            if (rc < 0) { report_error(); continue; }
            printf("ok");
            for (int k = 0; k < rc; k++) printf(" %d", bits[k]);
            printf("\n");
        } else if (strcmp(cmd, "rh") == 0 || strcmp(cmd, "ri") == 0) {
            uint16_t regs[125];
            int rc = cmd[1] == 'h' ? modbus_read_registers(ctx, addr, n, regs)
                                   : modbus_read_input_registers(ctx, addr, n, regs);
            if (rc < 0) { report_error(); continue; }
            printf("ok");
            for (int k = 0; k < rc; k++) printf(" %u", regs[k]);
            printf("\n");
        } else if (strcmp(cmd, "wc") == 0) {
            if (modbus_write_bit(ctx, addr, n) < 0) report_error(); else printf("ok\n");
        } else if (strcmp(cmd, "wh") == 0) {
            if (modbus_write_register(ctx, addr, n) < 0) report_error(); else printf("ok\n");
        } else if (strcmp(cmd, "wcs") == 0 || strcmp(cmd, "whs") == 0) {
            if (n < 1 || n > 2000 || i + n > argc) { printf("err bad arguments\n"); return 2; }
            uint8_t bits[2000];
            uint16_t regs[2000];
            for (int k = 0; k < n; k++) {
                bits[k] = (uint8_t)atoi(argv[i + k]);
                regs[k] = (uint16_t)atoi(argv[i + k]);
            }
            i += n;
            int rc = cmd[1] == 'c' ? modbus_write_bits(ctx, addr, n, bits)
                                   : modbus_write_registers(ctx, addr, n, regs);
            if (rc < 0) report_error(); else printf("ok\n");
        } else {
            printf("err unknown command %s\n", cmd);
            return 2;
        }
        fflush(stdout);
    }
    modbus_close(ctx);
    modbus_free(ctx);
    return 0;
}
