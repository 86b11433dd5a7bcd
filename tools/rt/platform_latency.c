/* What the platform gives a real-time thread, without the node: the baseline for the 800 Hz
 * loop's deadline misses (docs/node.md, "The 800 Hz loop under load").
 *
 *   cc -O2 -o /tmp/platform_latency tools/rt/platform_latency.c
 *   /tmp/platform_latency wake SECONDS [PRIORITY] [CPU]
 *   /tmp/platform_latency gap SECONDS [PRIORITY] [CPU]
 *
 * wake: a SCHED_FIFO thread with locked memory wakes every 1.25 ms on an absolute
 *       CLOCK_MONOTONIC deadline (clock_nanosleep TIMER_ABSTIME, timer slack 1 ns) and
 *       measures how late it woke (what the node calls jitter; > 1.25 ms is a deadline
 *       miss whatever the loop does). For wake-ups over 1 ms it sums the part the thread
 *       spent woken but waiting for a CPU (schedstat's run delay: another task kept the
 *       CPU, e.g. in a kernel section a PREEMPT_NONE kernel does not preempt) and the rest
 *       (the timer's interrupt came late: the vCPU was not running, or interrupts were off).
 * gap:  a SCHED_FIFO thread spins reading CLOCK_MONOTONIC for 200 ms of every second (under
 *       the kernel's RT throttling) and records every gap between two reads over 50 us: time
 *       the CPU was taken from a user-space thread that no task of the guest can preempt
 *       (interrupts, or the hypervisor running something else on the vCPU).
 * Per second it samples the guest's steal time (/proc/stat, all CPUs, in USER_HZ ticks), and
 * prints one JSON line: the histogram's tail, the count over 0.5 and 1 ms, the worst, the
 * steal time, and how many late events fell in seconds with and without steal.
 * PRIORITY defaults to 80 (the node's loop), CPU to none (not pinned). */
#define _GNU_SOURCE
#include <sched.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/prctl.h>
#include <time.h>
#include <fcntl.h>
#include <unistd.h>

static long long now_ns(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

/* The calling thread's time waiting on a run queue, ns (/proc/thread-self/schedstat). */
static long long run_delay_ns(int fd) {
  char buf[128];
  ssize_t n = pread(fd, buf, sizeof buf - 1, 0);
  long long run = 0, wait = 0;
  if (n <= 0) return 0;
  buf[n] = 0;
  sscanf(buf, "%lld %lld", &run, &wait);
  return wait;
}

static long long steal_ticks(void) {
  FILE *f = fopen("/proc/stat", "r");
  long long v[8] = {0};
  if (!f || fscanf(f, "cpu %lld %lld %lld %lld %lld %lld %lld %lld", &v[0], &v[1], &v[2], &v[3],
                   &v[4], &v[5], &v[6], &v[7]) != 8)
    v[7] = -1;
  if (f) fclose(f);
  return v[7];
}

#define BINS 20000 /* 1 us bins up to 20 ms */
static long long hist[BINS];

int main(int argc, char **argv) {
  if (argc < 3) {
    fprintf(stderr, "usage: %s wake|gap SECONDS [PRIORITY] [CPU]\n", argv[0]);
    return 2;
  }
  int gap = strcmp(argv[1], "gap") == 0;
  int seconds = atoi(argv[2]);
  int priority = argc > 3 ? atoi(argv[3]) : 80;
  if (argc > 4) {
    cpu_set_t set;
    CPU_ZERO(&set);
    CPU_SET(atoi(argv[4]), &set);
    if (sched_setaffinity(0, sizeof set, &set)) perror("sched_setaffinity");
  }
  prctl(PR_SET_TIMERSLACK, 1UL);
  if (mlockall(MCL_CURRENT | MCL_FUTURE)) perror("mlockall");
  struct sched_param p = {.sched_priority = priority};
  if (priority > 0 && sched_setscheduler(0, SCHED_FIFO, &p)) perror("SCHED_FIFO");
  memset(hist, 0, sizeof hist); /* touched before the measurement */
  const long long period = 1250000;
  long long events = 0, over_half = 0, over_ms = 0, worst = 0;
  long long late_in_steal_s = 0, late_in_quiet_s = 0, steal_s = 0, steal_total = 0;
  int schedstat = open("/proc/thread-self/schedstat", O_RDONLY);
  long long late_ms_total = 0, late_ms_run_delay = 0;
  long long start = now_ns(), steal_prev = steal_ticks();
  for (int s = 0; s < seconds; s++) {
    long long late_this_s = 0, second_end = start + (s + 1) * 1000000000LL;
    if (gap) {
      long long spin_end = second_end - 800000000LL, prev = now_ns();
      while (prev < spin_end) {
        long long t = now_ns(), d = t - prev;
        prev = t;
        if (d < 50000) continue;
        events++;
        hist[d / 1000 < BINS ? d / 1000 : BINS - 1]++;
        over_half += d > 500000;
        over_ms += d > 1000000;
        late_this_s += d > 500000;
        if (d > worst) worst = d;
      }
      struct timespec end = {second_end / 1000000000LL, second_end % 1000000000LL};
      clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &end, NULL);
    } else {
      for (long long k = 0;; k++) {
        long long deadline = start + s * 1000000000LL + k * period;
        if (deadline >= second_end) break;
        struct timespec ts = {deadline / 1000000000LL, deadline % 1000000000LL};
        long long delay_before = run_delay_ns(schedstat);
        clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL);
        long long d = now_ns() - deadline;
        if (d > 1000000) {
          late_ms_total += d;
          late_ms_run_delay += run_delay_ns(schedstat) - delay_before;
        }
        events++;
        hist[d / 1000 < BINS ? (d < 0 ? 0 : d / 1000) : BINS - 1]++;
        over_half += d > 500000;
        over_ms += d > 1000000;
        late_this_s += d > 500000;
        if (d > worst) worst = d;
      }
    }
    long long st = steal_ticks(), ds = st - steal_prev;
    steal_prev = st;
    steal_total += ds;
    steal_s += ds > 0;
    if (ds > 0)
      late_in_steal_s += late_this_s;
    else
      late_in_quiet_s += late_this_s;
  }
  long long acc = 0, p99 = 0, p999 = 0;
  for (int i = 0; i < BINS; i++) {
    acc += hist[i];
    if (!p99 && acc >= events * 0.99) p99 = i;
    if (!p999 && acc >= events * 0.999) p999 = i;
  }
  printf("{\"mode\": \"%s\", \"seconds\": %d, \"priority\": %d, \"events\": %lld, "
         "\"p99_us\": %lld, \"p999_us\": %lld, \"over_0.5ms\": %lld, \"over_1ms\": %lld, "
         "\"worst_ms\": %.3f, \"steal_ticks\": %lld, \"seconds_with_steal\": %lld, "
         "\"over_0.5ms_in_steal_seconds\": %lld, \"over_0.5ms_in_other_seconds\": %lld, "
         "\"over_1ms_total_ms\": %.1f, \"over_1ms_waiting_for_cpu_ms\": %.1f}\n",
         argv[1], seconds, priority, events, p99, p999, over_half, over_ms, worst / 1e6,
         steal_total, steal_s, late_in_steal_s, late_in_quiet_s, late_ms_total / 1e6,
         late_ms_run_delay / 1e6);
  return 0;
}
