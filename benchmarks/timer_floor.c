/* The timer floor of this machine, without Python: a thread that wakes at absolute
 * deadlines (clock_nanosleep TIMER_ABSTIME on CLOCK_MONOTONIC) and does nothing else.
 * Usage: timer_floor RATE_HZ SECONDS PRIO  (PRIO 0 = normal scheduling, else SCHED_FIFO).
 * Prints: "rt <0|1> ticks <n> missed <m> p50_us <x> p99_us <y> max_us <z>", where missed =
 * woken more than half a period after the deadline. Built and run by bench_loop.py. */
#include <sched.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

static int cmp(const void *a, const void *b) {
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

int main(int argc, char **argv) {
    double rate = argc > 1 ? atof(argv[1]) : 1000.0;
    double seconds = argc > 2 ? atof(argv[2]) : 10.0;
    int prio = argc > 3 ? atoi(argv[3]) : 0;
    int rt = 0;
    if (prio > 0) {
        struct sched_param sp = {.sched_priority = prio};
        rt = sched_setscheduler(0, SCHED_FIFO, &sp) == 0;
    }
    long n = (long)(rate * seconds), period_ns = (long)(1e9 / rate), missed = 0;
    double *late = malloc(sizeof(double) * (size_t)n);
    struct timespec next, now;
    clock_gettime(CLOCK_MONOTONIC, &next);
    for (long i = 0; i < n; i++) {
        next.tv_nsec += period_ns;
        while (next.tv_nsec >= 1000000000L) { next.tv_nsec -= 1000000000L; next.tv_sec++; }
        clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &next, NULL);
        clock_gettime(CLOCK_MONOTONIC, &now);
        late[i] = (now.tv_sec - next.tv_sec) * 1e6 + (now.tv_nsec - next.tv_nsec) / 1e3;
        if (late[i] > 0.5e6 / rate) missed++;
    }
    qsort(late, (size_t)n, sizeof(double), cmp);
    printf("rt %d ticks %ld missed %ld p50_us %.1f p99_us %.1f max_us %.1f\n", rt, n, missed,
           late[n / 2], late[(long)(0.99 * (n - 1))], late[n - 1]);
    free(late);
    return 0;
}
