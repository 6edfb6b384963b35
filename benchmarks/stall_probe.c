/*
 * stall_probe: does this machine stop running programs now and then?
 *
 * One thread per online CPU, pinned to it, SCHED_FIFO 99 where permitted (above the daemons'
 * 59-61), wakes every 1 ms (PERIOD_US; clock_nanosleep, absolute deadlines) and records each wake-up that
 * comes more than THRESHOLD_US after its deadline. Nothing in user space can delay such a thread:
 * a late wake-up is the kernel or the hypervisor (the VM not scheduled). When every CPU is late
 * at the same moment the whole machine stopped: a program frozen that long cannot tell it was.
 *
 *   gcc -O2 -pthread -o /tmp/stall_probe benchmarks/stall_probe.c
 *   /tmp/stall_probe SECONDS [THRESHOLD_US [PERIOD_US]]   # default threshold 5000 us, period 1000 us
 *
 * A longer period disturbs the programs it watches less (it preempts them at FIFO 99 on every CPU)
 * and still sees every stall longer than the period.
 *
 * Prints one line per late wake-up as it happens ("late CPU WALL_TIME LATE_MS") and, at the end,
 * one JSON line: per CPU the wake-ups, how many were late, the worst, and the machine's steal time
 * over the run (from /proc/stat; 0 where the hypervisor does not report it). Used by
 * benchmarks/bench_safety.py to tell a daemon's own stall from the machine's.
 */
#define _GNU_SOURCE
#include <pthread.h>
#include <sched.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/time.h>
#include <time.h>
#include <unistd.h>

static long period_ns = 1000000L; /* the third argument, in us (default 1000) */

struct probe {
    int cpu;
    double seconds;
    long threshold_ns;
    long wakeups;
    long late;
    long worst_ns;
    int fifo;
};

static pthread_mutex_t print_lock = PTHREAD_MUTEX_INITIALIZER;

static long ns_between(const struct timespec *a, const struct timespec *b)
{
    return (b->tv_sec - a->tv_sec) * 1000000000L + (b->tv_nsec - a->tv_nsec);
}

static void add_ns(struct timespec *t, long ns)
{
    t->tv_nsec += ns;
    while (t->tv_nsec >= 1000000000L) {
        t->tv_nsec -= 1000000000L;
        t->tv_sec += 1;
    }
}

static void *run(void *arg)
{
    struct probe *p = arg;
    cpu_set_t set;
    CPU_ZERO(&set);
    CPU_SET(p->cpu, &set);
    pthread_setaffinity_np(pthread_self(), sizeof set, &set);
    struct sched_param sp = {.sched_priority = 99};
    p->fifo = pthread_setschedparam(pthread_self(), SCHED_FIFO, &sp) == 0;

    struct timespec start, deadline, now;
    clock_gettime(CLOCK_MONOTONIC, &start);
    deadline = start;
    long total_ns = (long)(p->seconds * 1e9);
    for (;;) {
        add_ns(&deadline, period_ns);
        clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &deadline, NULL);
        clock_gettime(CLOCK_MONOTONIC, &now);
        p->wakeups++;
        long late = ns_between(&deadline, &now);
        if (late > p->worst_ns)
            p->worst_ns = late;
        if (late > p->threshold_ns) {
            p->late++;
            struct timeval tv;
            gettimeofday(&tv, NULL);
            struct tm tm;
            localtime_r(&tv.tv_sec, &tm);
            pthread_mutex_lock(&print_lock);
            printf("late cpu%d %02d:%02d:%02d.%03ld %.1f ms\n", p->cpu, tm.tm_hour, tm.tm_min,
                   tm.tm_sec, (long)(tv.tv_usec / 1000), late / 1e6);
            fflush(stdout);
            pthread_mutex_unlock(&print_lock);
            deadline = now; /* one report per stall, not one per missed period */
        }
        if (ns_between(&start, &now) >= total_ns)
            break;
    }
    return NULL;
}

static long long steal_ticks(void)
{
    FILE *f = fopen("/proc/stat", "r");
    if (!f)
        return 0;
    unsigned long long v[8] = {0};
    int n = fscanf(f, "cpu %llu %llu %llu %llu %llu %llu %llu %llu", &v[0], &v[1], &v[2], &v[3],
                   &v[4], &v[5], &v[6], &v[7]);
    fclose(f);
    return n == 8 ? (long long)v[7] : 0;
}

int main(int argc, char **argv)
{
    if (argc < 2) {
        fprintf(stderr, "usage: %s SECONDS [THRESHOLD_US [PERIOD_US]]\n", argv[0]);
        return 2;
    }
    double seconds = atof(argv[1]);
    long threshold_us = argc > 2 ? atol(argv[2]) : 5000;
    long period_us = argc > 3 ? atol(argv[3]) : 1000;
    if (seconds <= 0 || threshold_us <= 0 || period_us <= 0) {
        fprintf(stderr, "stall_probe: SECONDS, THRESHOLD_US and PERIOD_US must be positive\n");
        return 2;
    }
    period_ns = period_us * 1000L;
    int ncpu = (int)sysconf(_SC_NPROCESSORS_ONLN);
    if (ncpu < 1)
        ncpu = 1;
    struct probe *probes = calloc((size_t)ncpu, sizeof *probes);
    pthread_t *threads = calloc((size_t)ncpu, sizeof *threads);
    if (!probes || !threads)
        return 1;
    long long steal0 = steal_ticks();
    for (int i = 0; i < ncpu; i++) {
        probes[i] = (struct probe){.cpu = i, .seconds = seconds, .threshold_ns = threshold_us * 1000};
        if (pthread_create(&threads[i], NULL, run, &probes[i]) != 0) {
            perror("stall_probe: pthread_create");
            return 1;
        }
    }
    for (int i = 0; i < ncpu; i++)
        pthread_join(threads[i], NULL);
    long long steal = steal_ticks() - steal0;
    printf("{\"seconds\": %.1f, \"threshold_us\": %ld, \"steal_s\": %.2f, \"cpus\": [", seconds,
           threshold_us, (double)steal / (double)sysconf(_SC_CLK_TCK));
    for (int i = 0; i < ncpu; i++)
        printf("%s{\"cpu\": %d, \"fifo\": %s, \"wakeups\": %ld, \"late\": %ld, \"worst_ms\": %.3f}",
               i ? ", " : "", probes[i].cpu, probes[i].fifo ? "true" : "false", probes[i].wakeups,
               probes[i].late, probes[i].worst_ns / 1e6);
    printf("]}\n");
    return 0;
}
