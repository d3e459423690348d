/*
 * stipi_simavr_harness -- hardware-in-the-loop in simulation for the STIP-I probe firmware.
 *
 * Owns: running a firmware ELF on libsimavr as an ATmega32u4 at 8 MHz, driving the load-cell
 * ADC input from a voltage waveform defined in SIMULATED time, bridging the firmware's
 * hardware UART (simavr UART '1' = Arduino Serial1) to a pseudo-terminal, and reporting
 * simulated time, speed and watched registers on stdout. It does not decode the protocol
 * (the host does that through the pty) and it does not model the USB CDC link. With --nrf51
 * the simulated nRF51822 of tests/firmware/nrf51_sim (written from Adafruit's SDEP.md) sits
 * behind simavr's SPI and the Feather's CS/IRQ/RST pins, with a central that connects at
 * --ble-connect-s and drains the module's TX FIFO; what it receives goes to --ble-out.
 *
 * stdout is line-oriented; every line the harness writes starts with an upper-case keyword
 * followed by key=value fields (simavr's own log goes to stderr):
 *
 *   PTY path=/dev/pts/N                         the host opens this (115200 8N1 raw)
 *   START sim_s=0.000000                        CPU released (after --wait-host if given)
 *   UART sim_s=.. cycles_per_byte=.. bytes_per_s=..  byte time of the bridged UART (on change)
 *   TIME sim_s=.. wall_s=.. speed=.. cycles=..  every --report-interval simulated seconds
 *   ADC sim_s=.. channel=.. mv=..               every conversion of the load-cell channel
 *                                               starts (--log-adc)
 *   AUX sim_s=.. channel=..                     every conversion of another channel starts
 *                                               (--log-adc; e.g. the supply reading)
 *   REG sim_s=.. name=.. addr=0x.. value=..     a watched data byte changed (--watch)
 *   BLE sim_s=.. event=connected|summary ..      the central connected; module counters
 *                                               (summary, after EXIT) with --nrf51
 *   EXIT reason=.. sim_s=.. wall_s=.. speed=.. tx_bytes=.. rx_bytes=.. pauses=.. pause_wall_s=..
 *        discarded=..                           (bytes sent while no host had the pty open)
 *                                               simulation stopped; the pty stays open until
 *                                               the host hangs up or --linger expires
 *
 * Simulated time is avr->cycle / frequency; the firmware's micros() counts the same clock.
 * The ADC input is set just in time: on ADC_IRQ_OUT_TRIGGER (conversion start, where the real
 * chip samples and holds) the harness evaluates the waveform at the current simulated time
 * and raises ADC_IRQ_ADC0+channel with the value in millivolts (integer, as simavr takes it).
 *
 * The UART bridge is single-threaded and lossless: bytes the firmware sends are queued and
 * written to the pty master whenever it accepts them; if the host falls behind by more than
 * --max-backlog bytes the simulation pauses until the host has read them (counted as
 * "pauses"). Bytes from the host are fed to the UART only while simavr signals XON, so its
 * 64-byte receive FIFO never overruns; simavr then delivers them at the configured baud rate.
 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <getopt.h>
#include <math.h>
#include <poll.h>
#include <signal.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "avr_adc.h"
#include "avr_ioport.h"
#include "avr_spi.h"
#include "avr_uart.h"
#include "sim_avr.h"
#include "sim_elf.h"
#include "sim_irq.h"
#include "sim_cycle_timers.h"

#include "nrf51_sim.h" /* tests/firmware/nrf51_sim: the simulated module, from SDEP.md */

#define MAX_WATCH 16
#define OUT_RING_SIZE (1u << 20) /* bytes queued from the firmware towards the host */
#define IN_RING_SIZE (1u << 14)  /* bytes queued from the host towards the firmware */
#define BLE_TICK_PER_S 10000     /* --nrf51: module time advanced every 100 us at least */

/* ------------------------------------------------------------------------------------------ */
/* Waveform: millivolts as a function of simulated time [s].                                  */

enum wave_kind { WAVE_CONST, WAVE_RAMP, WAVE_SINE, WAVE_TRIANGLE, WAVE_FILE };

typedef struct {
	enum wave_kind kind;
	double a, b, c;   /* parameters, meaning per kind (see usage) */
	double *t_s;      /* WAVE_FILE: strictly increasing times [s] */
	double *mv;       /* WAVE_FILE: millivolts at t_s */
	size_t n;         /* WAVE_FILE: number of points */
	size_t cursor;    /* WAVE_FILE: segment of the last lookup (time only moves forward) */
} wave_t;

static void die(const char *fmt, ...) __attribute__((noreturn, format(printf, 1, 2)));
static void die(const char *fmt, ...)
{
	va_list ap;
	va_start(ap, fmt);
	fputs("stipi_simavr_harness: error: ", stderr);
	vfprintf(stderr, fmt, ap);
	fputc('\n', stderr);
	va_end(ap);
	exit(2);
}

static void wave_load_file(wave_t *w, const char *path)
{
	FILE *f = fopen(path, "r");
	if (!f)
		die("cannot open waveform file %s: %s", path, strerror(errno));
	size_t cap = 256;
	w->t_s = malloc(cap * sizeof(double));
	w->mv = malloc(cap * sizeof(double));
	char line[256];
	unsigned lineno = 0;
	while (fgets(line, sizeof line, f)) {
		lineno++;
		char *p = line;
		while (*p == ' ' || *p == '\t')
			p++;
		if (*p == '#' || *p == '\n' || *p == '\r' || *p == 0)
			continue;
		for (char *q = p; *q; q++)
			if (*q == ',')
				*q = ' ';
		double t, v;
		char extra;
		if (sscanf(p, "%lf %lf %c", &t, &v, &extra) != 2)
			die("%s:%u: expected 'time_s millivolts', got: %s", path, lineno, line);
		if (!isfinite(t) || !isfinite(v))
			die("%s:%u: time and millivolts must be finite", path, lineno);
		if (w->n && t <= w->t_s[w->n - 1])
			die("%s:%u: time %.9g s is not after the previous point (%.9g s)", path, lineno,
			    t, w->t_s[w->n - 1]);
		if (w->n == cap) {
			cap *= 2;
			w->t_s = realloc(w->t_s, cap * sizeof(double));
			w->mv = realloc(w->mv, cap * sizeof(double));
		}
		w->t_s[w->n] = t;
		w->mv[w->n] = v;
		w->n++;
	}
	fclose(f);
	if (!w->n)
		die("%s: no (time_s, millivolts) points", path);
}

static void wave_parse(wave_t *w, const char *spec)
{
	memset(w, 0, sizeof *w);
	if (!strncmp(spec, "file:", 5)) {
		w->kind = WAVE_FILE;
		wave_load_file(w, spec + 5);
		return;
	}
	char name[16];
	int consumed = 0;
	if (sscanf(spec, "%15[a-z]%n", name, &consumed) != 1)
		die("bad --wave '%s'", spec);
	const char *args = spec + consumed;
	int n = 0;
	double a = 0, b = 0, c = 0;
	if (*args == ':')
		n = sscanf(args, ":%lf:%lf:%lf", &a, &b, &c);
	if (!strcmp(name, "const") && n == 1)
		w->kind = WAVE_CONST;
	else if (!strcmp(name, "ramp") && n == 3 && c > 0)
		w->kind = WAVE_RAMP;
	else if (!strcmp(name, "sine") && n == 3 && c > 0)
		w->kind = WAVE_SINE;
	else if (!strcmp(name, "triangle") && n == 3 && c > 0)
		w->kind = WAVE_TRIANGLE;
	else
		die("bad --wave '%s' (want const:MV | ramp:MV0:MV1:DURATION_S | "
		    "sine:OFFSET_MV:AMPLITUDE_MV:FREQ_HZ | triangle:LOW_MV:HIGH_MV:PERIOD_S | file:PATH)",
		    spec);
	w->a = a;
	w->b = b;
	w->c = c;
}

static double wave_mv(wave_t *w, double t_s)
{
	switch (w->kind) {
	case WAVE_CONST:
		return w->a;
	case WAVE_RAMP: /* a -> b linearly over c seconds, then hold b */
		if (t_s >= w->c)
			return w->b;
		return w->a + (w->b - w->a) * (t_s / w->c);
	case WAVE_SINE: /* a + b sin(2 pi c t) */
		return w->a + w->b * sin(2.0 * M_PI * w->c * t_s);
	case WAVE_TRIANGLE: { /* a at t = 0, b at c/2, a at c, periodic */
		double ph = fmod(t_s, w->c) / w->c;
		double up = ph < 0.5 ? 2.0 * ph : 2.0 - 2.0 * ph;
		return w->a + (w->b - w->a) * up;
	}
	case WAVE_FILE: {
		if (t_s <= w->t_s[0])
			return w->mv[0];
		if (t_s >= w->t_s[w->n - 1])
			return w->mv[w->n - 1];
		if (w->t_s[w->cursor] > t_s)
			w->cursor = 0;
		while (w->cursor + 1 < w->n && w->t_s[w->cursor + 1] <= t_s)
			w->cursor++;
		size_t i = w->cursor;
		double f = (t_s - w->t_s[i]) / (w->t_s[i + 1] - w->t_s[i]);
		return w->mv[i] + (w->mv[i + 1] - w->mv[i]) * f;
	}
	}
	return 0.0;
}

/* ------------------------------------------------------------------------------------------ */
/* State                                                                                      */

typedef struct {
	uint16_t addr;
	char name[32];
	int last; /* -1 before the first sample */
} watch_t;

static struct {
	avr_t *avr;
	wave_t wave;
	int adc_channel;
	int log_adc;
	avr_irq_t *adc_in;
	avr_irq_t *uart_in;

	int master;          /* pty master fd */
	char slave_name[64];
	int host_seen;       /* host has opened the pty */

	uint8_t *out;        /* ring towards the host */
	size_t out_head, out_len;
	uint8_t in[IN_RING_SIZE]; /* ring towards the firmware */
	size_t in_head, in_len;
	int xon;             /* simavr UART accepts input */
	int feeding;         /* re-entrancy guard for uart_feed() */

	uint64_t tx_bytes, rx_bytes, pauses, discarded;
	double pause_wall_s;
	watch_t watch[MAX_WATCH];
	int n_watch;

	double noise_mv;             /* --noise-mv: gaussian noise added per conversion [mV rms] */
	uint64_t rng;                /* xorshift64* state (--seed) */

	/* --nrf51: the simulated module behind SPI, CS (D8 = PB4), IRQ (D7 = PE6), RST (D4 = PD4) */
	int ble;
	nrf51_sim nrf;
	avr_irq_t *spi_in;           /* MISO byte into the AVR's SPI */
	avr_irq_t *ble_irq_pin;      /* PE6 input */
	int ble_irq_level;           /* last level driven, -1 before the first */
	double ble_connect_s;        /* central connects at this simulated time (< 0: never) */
	FILE *ble_out;               /* bytes the central received (--ble-out) */
	uint64_t ble_rx_bytes, spi_bytes, cs_falls;
	uint64_t cs_fall_cycle, cs_low_cycles, cs_low_max_cycles; /* CS-low time (transactions) */

	avr_uart_t *uart;            /* the bridged UART's simavr state */
	avr_cycle_count_t uart_cpb;  /* cycles per byte last reported */
	double uart_bytes_per_s;     /* --uart-bytes-per-s override, 0 = firmware's baud */
} H;

static volatile sig_atomic_t g_signal;

static void on_signal(int sig) { g_signal = sig; }

static double now_wall(void)
{
	struct timespec ts;
	clock_gettime(CLOCK_MONOTONIC, &ts);
	return ts.tv_sec + ts.tv_nsec * 1e-9;
}

static double sim_s(void) { return (double)H.avr->cycle / (double)H.avr->frequency; }

/* ------------------------------------------------------------------------------------------ */
/* simavr hooks                                                                               */

/* Deterministic gaussian noise (xorshift64* + Box-Muller), seeded by --seed. */
static double uniform01(void)
{
	H.rng ^= H.rng >> 12;
	H.rng ^= H.rng << 25;
	H.rng ^= H.rng >> 27;
	return ((H.rng * 0x2545F4914F6CDD1DULL) >> 11) * (1.0 / 9007199254740992.0);
}

static double gauss(void)
{
	double u = uniform01();
	if (u < 1e-300)
		u = 1e-300;
	return sqrt(-2.0 * log(u)) * cos(2.0 * M_PI * uniform01());
}

/* ---- the simulated nRF51822 (--nrf51) ------------------------------------------------------ */

static uint32_t sim_us(void)
{
	return (uint32_t)((H.avr->cycle * 1000000ULL) / H.avr->frequency);
}

/* Advance the module to now and drive the IRQ pin when its level changed. */
static void ble_sync(void)
{
	nrf51_sim_advance(&H.nrf, sim_us());
	int level = nrf51_sim_irq(&H.nrf);
	if (level != H.ble_irq_level) {
		H.ble_irq_level = level;
		avr_raise_irq(H.ble_irq_pin, (uint32_t)level);
	}
}

/* The AVR's SPI finished shifting a byte out (master): the module shifts one back. */
static void ble_spi_hook(struct avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	(void)param;
	nrf51_sim_advance(&H.nrf, sim_us());
	uint8_t miso = nrf51_sim_xfer(&H.nrf, (uint8_t)value);
	H.spi_bytes++;
	avr_raise_irq(H.spi_in, miso);
	ble_sync();
}

static void ble_cs_hook(struct avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	(void)param;
	nrf51_sim_advance(&H.nrf, sim_us());
	if (!value && !H.nrf.selected) {
		H.cs_falls++;
		H.cs_fall_cycle = H.avr->cycle;
	} else if (value && H.nrf.selected) {
		uint64_t d = H.avr->cycle - H.cs_fall_cycle;
		H.cs_low_cycles += d;
		if (d > H.cs_low_max_cycles)
			H.cs_low_max_cycles = d;
	}
	nrf51_sim_select(&H.nrf, value == 0);
	ble_sync();
}

static void ble_rst_hook(struct avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	(void)param;
	nrf51_sim_advance(&H.nrf, sim_us());
	nrf51_sim_reset(&H.nrf, value == 0);
	ble_sync();
}

static void ble_notify(void *ctx, const uint8_t *data, uint16_t len)
{
	(void)ctx;
	H.ble_rx_bytes += len;
	if (H.ble_out)
		fwrite(data, 1, len, H.ble_out);
}

/* Every 1/BLE_TICK_PER_S simulated (and at every SPI byte and CS edge): processing delays end, the central drains the FIFO, IRQ follows. */
static avr_cycle_count_t ble_tick(struct avr_t *avr, avr_cycle_count_t when, void *param)
{
	(void)avr;
	(void)param;
	if (H.ble_connect_s >= 0 && !H.nrf.connected && sim_s() >= H.ble_connect_s) {
		nrf51_sim_set_connected(&H.nrf, 1);
		printf("BLE sim_s=%.6f event=connected\n", sim_s());
	}
	ble_sync();
	return when + H.avr->frequency / BLE_TICK_PER_S;
}

static void adc_trigger_hook(struct avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	(void)param;
	union {
		avr_adc_mux_t mux;
		uint32_t v;
	} e = {.v = value};
	double t = sim_s();
	double mv = wave_mv(&H.wave, t);
	if (H.noise_mv > 0 && e.mux.kind == ADC_MUX_SINGLE && (int)e.mux.src == H.adc_channel)
		mv += H.noise_mv * gauss();
	long imv = lround(mv);
	if (imv < 0)
		imv = 0;
	if (imv > 65535)
		imv = 65535;
	avr_raise_irq(H.adc_in, (uint32_t)imv);
	if (H.log_adc && e.mux.kind == ADC_MUX_SINGLE && (int)e.mux.src == H.adc_channel)
		printf("ADC sim_s=%.9f channel=%d mv=%ld\n", t, H.adc_channel, imv);
	else if (H.log_adc && e.mux.kind == ADC_MUX_SINGLE)
		printf("AUX sim_s=%.9f channel=%d\n", t, (int)e.mux.src);
}

static void uart_out_hook(struct avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	(void)param;
	if (H.out_len == OUT_RING_SIZE)
		die("host backlog ring overflow (%u bytes); this is a harness bug", OUT_RING_SIZE);
	H.out[(H.out_head + H.out_len) % OUT_RING_SIZE] = (uint8_t)value;
	H.out_len++;
	H.tx_bytes++;
}

static void uart_feed(void)
{
	if (H.feeding)
		return;
	H.feeding = 1;
	while (H.xon && H.in_len) {
		uint8_t b = H.in[H.in_head];
		H.in_head = (H.in_head + 1) % IN_RING_SIZE;
		H.in_len--;
		H.rx_bytes++;
		avr_raise_irq(H.uart_in, b); /* may call uart_xoff_hook() synchronously */
	}
	H.feeding = 0;
}

static void uart_xon_hook(struct avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	(void)value;
	(void)param;
	H.xon = 1;
	uart_feed();
}

static void uart_xoff_hook(struct avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	(void)param;
	if (value)
		H.xon = 0;
}

/* Sleeping firmware: simavr's raw sleep callback would usleep() in wall time; run free. */
static void sleep_hook(avr_t *avr, avr_cycle_count_t how_long)
{
	(void)avr;
	(void)how_long;
}

static void logger(avr_t *avr, const int level, const char *fmt, va_list ap)
{
	if (avr && level > avr->log)
		return;
	fputs("simavr: ", stderr);
	vfprintf(stderr, fmt, ap);
}

/* simavr's UART state, found among the core's IO modules (avr_uart_t starts with its avr_io_t). */
static avr_uart_t *find_uart(char name)
{
	for (avr_io_t *io = H.avr->io_port; io; io = io->next)
		if (io->kind && !strcmp(io->kind, "uart") &&
		    io->irq_ioctl_get == (uint32_t)AVR_IOCTL_UART_GETIRQ(name))
			return (avr_uart_t *)io;
	return NULL;
}

/* Report the UART byte time whenever the firmware (re)configures it, and apply the
   --uart-bytes-per-s override. simavr 1.6 times a byte as 1 start + 8 data + 1 parity +
   stop bit(s) whether parity is enabled or not: 11 bit times for 8N1, 10 % slower than the
   chip, so the simulated link is slightly pessimistic. */
static void uart_police(void)
{
	if (!H.uart)
		return;
	if (H.uart_bytes_per_s > 0) {
		avr_cycle_count_t want = (avr_cycle_count_t)llround(H.avr->frequency / H.uart_bytes_per_s);
		if (want < 1)
			want = 1;
		H.uart->cycles_per_byte = want;
	}
	if (H.uart->cycles_per_byte != H.uart_cpb) {
		H.uart_cpb = H.uart->cycles_per_byte;
		printf("UART sim_s=%.6f cycles_per_byte=%llu bytes_per_s=%.1f\n", sim_s(),
		       (unsigned long long)H.uart_cpb, (double)H.avr->frequency / (double)H.uart_cpb);
	}
}

/* ------------------------------------------------------------------------------------------ */
/* pty                                                                                        */

static void pty_open(const char *link_path)
{
	H.master = posix_openpt(O_RDWR | O_NOCTTY | O_NONBLOCK);
	if (H.master < 0 || grantpt(H.master) || unlockpt(H.master))
		die("cannot create a pty: %s", strerror(errno));
	const char *name = ptsname(H.master);
	if (!name)
		die("ptsname failed: %s", strerror(errno));
	snprintf(H.slave_name, sizeof H.slave_name, "%s", name);
	struct termios t;
	if (tcgetattr(H.master, &t) == 0) {
		cfmakeraw(&t);
		cfsetspeed(&t, B115200);
		tcsetattr(H.master, TCSANOW, &t);
	}
	/* Open and close the slave once: from then on the master reports POLLHUP exactly while
	   no host holds the slave open, which is how connect and hang-up are detected. */
	int s = open(H.slave_name, O_RDWR | O_NOCTTY);
	if (s < 0)
		die("cannot open %s: %s", H.slave_name, strerror(errno));
	close(s);
	if (link_path) {
		unlink(link_path);
		if (symlink(H.slave_name, link_path))
			die("cannot link %s -> %s: %s", link_path, H.slave_name, strerror(errno));
	}
}

/* Move bytes between the rings and the pty. Returns the poll revents seen. */
static short pty_service(int timeout_ms)
{
	struct pollfd p = {.fd = H.master, .events = POLLIN};
	if (H.out_len)
		p.events |= POLLOUT;
	if (poll(&p, 1, timeout_ms) < 0) {
		if (errno == EINTR)
			return 0;
		die("poll: %s", strerror(errno));
	}
	if (!(p.revents & POLLHUP))
		H.host_seen = 1;
	if (p.revents & POLLIN) {
		uint8_t buf[1024];
		size_t room = IN_RING_SIZE - H.in_len;
		if (room > sizeof buf)
			room = sizeof buf;
		if (room) {
			ssize_t r = read(H.master, buf, room);
			for (ssize_t i = 0; i < r; i++) {
				H.in[(H.in_head + H.in_len) % IN_RING_SIZE] = buf[i];
				H.in_len++;
			}
		}
	}
	if (p.revents & POLLHUP) {
		/* No host holds the pty: like a UART with nothing attached, the bytes go nowhere. */
		H.discarded += H.out_len;
		H.out_head = (H.out_head + H.out_len) % OUT_RING_SIZE;
		H.out_len = 0;
	}
	while (H.out_len) {
		size_t chunk = OUT_RING_SIZE - H.out_head;
		if (chunk > H.out_len)
			chunk = H.out_len;
		ssize_t w = write(H.master, H.out + H.out_head, chunk);
		if (w <= 0)
			break;
		H.out_head = (H.out_head + (size_t)w) % OUT_RING_SIZE;
		H.out_len -= (size_t)w;
	}
	uart_feed();
	return p.revents;
}

/* ------------------------------------------------------------------------------------------ */

static void usage(FILE *f)
{
	fputs("usage: stipi_simavr_harness [options] FIRMWARE.elf\n"
	      "  --mcu NAME              simavr core (default atmega32u4)\n"
	      "  --freq HZ               CPU clock (default 8000000)\n"
	      "  --vcc-mv MV             VCC = AVCC = AREF in millivolts (default 3300)\n"
	      "  --adc-channel N         ADC input wired to the load cell (default 7 = A0 on the "
	      "32u4)\n"
	      "  --wave SPEC             const:MV | ramp:MV0:MV1:DURATION_S |\n"
	      "                          sine:OFFSET_MV:AMPLITUDE_MV:FREQ_HZ |\n"
	      "                          triangle:LOW_MV:HIGH_MV:PERIOD_S | file:PATH (lines 'time_s "
	      "mV',\n"
	      "                          linear interpolation, held at the ends); default const:1650\n"
	      "  --uart C                simavr UART name bridged to the pty (default 1 = Serial1)\n"
	      "  --uart-bytes-per-s N    override the UART's byte rate (both directions) to model a\n"
	      "                          slower link; default: the firmware's baud as simavr times "
	      "it\n"
	      "  --sim-time S            stop after S simulated seconds (default 0 = run until "
	      "killed)\n"
	      "  --report-interval S     TIME line every S simulated seconds (default 0.1)\n"
	      "  --speed X               at most X times real time (default 0 = as fast as "
	      "possible)\n"
	      "  --wait-host             hold the CPU in reset until the host has opened the pty "
	      "and\n"
	      "                          sent at least one byte (a 0x00 is harmless to the "
	      "protocol)\n"
	      "  --no-exit-on-hangup     keep running when the host closes the pty\n"
	      "  --max-backlog BYTES     pause the simulation while more bytes wait for the host\n"
	      "                          (default 4096)\n"
	      "  --log-adc               print an ADC line at every conversion start\n"
	      "  --noise-mv SIGMA        add gaussian noise of SIGMA mV rms to every load-cell\n"
	      "                          conversion (dither; default 0)\n"
	      "  --seed N                noise seed (default 1)\n"
	      "  --hold CH:MV            hold ADC input CH (0..7) at MV millivolts (e.g. 6:2375\n"
	      "                          for a 4.75 V rail through a 1:2 divider on A1)\n"
	      "  --nrf51                 attach the simulated nRF51822 (tests/firmware/nrf51_sim)\n"
	      "                          behind SPI, CS D8, IRQ D7, RST D4\n"
	      "  --ble-connect-s S       a central connects at S simulated seconds (default 0)\n"
	      "  --ble-interval-us US    central's connection interval (default 30000)\n"
	      "  --ble-bytes-per-event B bytes the central takes per interval (default 20)\n"
	      "  --ble-process-us US     module's processing time per command (default 5000)\n"
	      "  --ble-out PATH          write the bytes the central received to PATH\n"
	      "  --watch ADDR[:NAME]     print a REG line when the data byte at ADDR changes "
	      "(repeatable)\n"
	      "  --pty-link PATH         also create a symlink PATH -> the pty slave\n"
	      "  --linger S              after stopping, keep the pty open until the host hangs up "
	      "or\n"
	      "                          S wall seconds pass, so it can read everything "
	      "(default 5)\n",
	      f);
}

int main(int argc, char **argv)
{
	const char *mcu = "atmega32u4";
	uint32_t freq = 8000000, vcc_mv = 3300;
	const char *wave_spec = "const:1650";
	char uart_name = '1';
	double sim_limit_s = 0, report_s = 0.1, speed = 0;
	int wait_host = 0, exit_on_hangup = 1;
	size_t max_backlog = 4096;
	double linger_s = 5.0;
	const char *pty_link = NULL;
	H.adc_channel = 7;
	H.rng = 1;
	uint32_t ble_interval_us = 30000, ble_process_us = 5000;
	uint16_t ble_bpe = 20;
	const char *ble_out = NULL;
	int hold_ch = -1;
	unsigned hold_mv = 0;

	enum {
		O_MCU = 256, O_FREQ, O_VCC, O_CHAN, O_WAVE, O_UART, O_SIMT, O_REP, O_SPEED, O_WAIT,
		O_NOHUP, O_BACKLOG, O_LOGADC, O_WATCH, O_LINK, O_LINGER, O_UBPS, O_HELP, O_NOISE,
		O_SEED, O_HOLD, O_NRF, O_BLECONN, O_BLEINT, O_BLEBPE, O_BLEPROC, O_BLEOUT
	};
	static const struct option opts[] = {
	    {"mcu", 1, 0, O_MCU},           {"freq", 1, 0, O_FREQ},
	    {"vcc-mv", 1, 0, O_VCC},        {"adc-channel", 1, 0, O_CHAN},
	    {"wave", 1, 0, O_WAVE},         {"uart", 1, 0, O_UART},
	    {"sim-time", 1, 0, O_SIMT},     {"report-interval", 1, 0, O_REP},
	    {"speed", 1, 0, O_SPEED},       {"wait-host", 0, 0, O_WAIT},
	    {"no-exit-on-hangup", 0, 0, O_NOHUP}, {"max-backlog", 1, 0, O_BACKLOG},
	    {"log-adc", 0, 0, O_LOGADC},    {"watch", 1, 0, O_WATCH},
	    {"pty-link", 1, 0, O_LINK},     {"linger", 1, 0, O_LINGER},
	    {"uart-bytes-per-s", 1, 0, O_UBPS},
	    {"noise-mv", 1, 0, O_NOISE},    {"seed", 1, 0, O_SEED},
	    {"hold", 1, 0, O_HOLD},
	    {"nrf51", 0, 0, O_NRF},         {"ble-connect-s", 1, 0, O_BLECONN},
	    {"ble-interval-us", 1, 0, O_BLEINT}, {"ble-bytes-per-event", 1, 0, O_BLEBPE},
	    {"ble-process-us", 1, 0, O_BLEPROC}, {"ble-out", 1, 0, O_BLEOUT},
	    {"help", 0, 0, O_HELP},
	    {0, 0, 0, 0}};
	int c;
	while ((c = getopt_long(argc, argv, "h", opts, NULL)) != -1) {
		switch (c) {
		case O_MCU: mcu = optarg; break;
		case O_FREQ: freq = (uint32_t)strtoul(optarg, NULL, 0); break;
		case O_VCC: vcc_mv = (uint32_t)strtoul(optarg, NULL, 0); break;
		case O_CHAN: H.adc_channel = atoi(optarg); break;
		case O_WAVE: wave_spec = optarg; break;
		case O_UART: uart_name = optarg[0]; break;
		case O_SIMT: sim_limit_s = atof(optarg); break;
		case O_REP: report_s = atof(optarg); break;
		case O_SPEED: speed = atof(optarg); break;
		case O_WAIT: wait_host = 1; break;
		case O_NOHUP: exit_on_hangup = 0; break;
		case O_BACKLOG: max_backlog = strtoul(optarg, NULL, 0); break;
		case O_LOGADC: H.log_adc = 1; break;
		case O_WATCH: {
			if (H.n_watch == MAX_WATCH)
				die("at most %d --watch", MAX_WATCH);
			watch_t *w = &H.watch[H.n_watch++];
			char *end;
			unsigned long a = strtoul(optarg, &end, 0);
			if (end == optarg || a > 0xffff)
				die("bad --watch '%s' (want ADDR[:NAME], e.g. 0x8A:OCR1BL)", optarg);
			w->addr = (uint16_t)a;
			snprintf(w->name, sizeof w->name, "%s", *end == ':' ? end + 1 : optarg);
			w->last = -1;
			break;
		}
		case O_LINK: pty_link = optarg; break;
		case O_LINGER: linger_s = atof(optarg); break;
		case O_UBPS: H.uart_bytes_per_s = atof(optarg); break;
		case O_NOISE: H.noise_mv = atof(optarg); break;
		case O_SEED: H.rng = strtoull(optarg, NULL, 0); break;
		case O_HOLD:
			if (sscanf(optarg, "%d:%u", &hold_ch, &hold_mv) != 2 || hold_ch < 0 || hold_ch > 7)
				die("bad --hold '%s' (want CHANNEL:MV, channel 0..7)", optarg);
			break;
		case O_NRF: H.ble = 1; break;
		case O_BLECONN: H.ble_connect_s = atof(optarg); break;
		case O_BLEINT: ble_interval_us = (uint32_t)strtoul(optarg, NULL, 0); break;
		case O_BLEBPE: ble_bpe = (uint16_t)strtoul(optarg, NULL, 0); break;
		case O_BLEPROC: ble_process_us = (uint32_t)strtoul(optarg, NULL, 0); break;
		case O_BLEOUT: ble_out = optarg; break;
		case O_HELP:
		case 'h': usage(stdout); return 0;
		default: usage(stderr); return 2;
		}
	}
	if (optind != argc - 1) {
		usage(stderr);
		return 2;
	}
	if (H.adc_channel < 0 || H.adc_channel > 7)
		die("--adc-channel %d: simavr 1.6 models external inputs ADC0..ADC7 only", H.adc_channel);
	if (!freq || !vcc_mv || report_s <= 0 || speed < 0 || sim_limit_s < 0 || !max_backlog)
		die("--freq, --vcc-mv, --report-interval, --max-backlog must be > 0; --speed and "
		    "--sim-time >= 0");
	wave_parse(&H.wave, wave_spec);
	if (!H.rng)
		H.rng = 1;
	setvbuf(stdout, NULL, _IOLBF, 0);
	avr_global_logger_set(logger);

	/* The struct's tail depends on ELF_SYMBOLS; a zeroed oversized buffer is layout-safe. */
	static union {
		elf_firmware_t f;
		uint8_t pad[sizeof(elf_firmware_t) + 256];
	} fw;
	if (elf_read_firmware(argv[optind], &fw.f))
		die("cannot read firmware ELF %s", argv[optind]);
	snprintf(fw.f.mmcu, sizeof fw.f.mmcu, "%s", mcu);
	fw.f.frequency = freq;
	fw.f.vcc = fw.f.avcc = fw.f.aref = vcc_mv;

	H.avr = avr_make_mcu_by_name(mcu);
	if (!H.avr)
		die("simavr does not know mcu '%s'", mcu);
	avr_init(H.avr);
	H.avr->log = LOG_ERROR;
	avr_load_firmware(H.avr, &fw.f);
	H.avr->frequency = freq;
	H.avr->vcc = H.avr->avcc = H.avr->aref = vcc_mv;
	H.avr->sleep = sleep_hook;
	H.avr->gdb_port = 0;

	/* ADC: value just in time at every conversion start. */
	H.adc_in = avr_io_getirq(H.avr, AVR_IOCTL_ADC_GETIRQ, ADC_IRQ_ADC0 + H.adc_channel);
	avr_irq_t *trig = avr_io_getirq(H.avr, AVR_IOCTL_ADC_GETIRQ, ADC_IRQ_OUT_TRIGGER);
	if (!H.adc_in || !trig)
		die("mcu %s has no ADC", mcu);
	avr_irq_register_notify(trig, adc_trigger_hook, NULL);
	avr_raise_irq(H.adc_in, (uint32_t)lround(fmax(0.0, wave_mv(&H.wave, 0.0))));
	if (hold_ch >= 0) /* a second input held constant, e.g. the 5 V sense divider on A1 = ADC6 */
		avr_raise_irq(avr_io_getirq(H.avr, AVR_IOCTL_ADC_GETIRQ, ADC_IRQ_ADC0 + hold_ch),
		              hold_mv);

	if (H.ble) {
		nrf51_sim_init(&H.nrf);
		H.nrf.process_us = ble_process_us;
		H.nrf.conn_interval_us = ble_interval_us;
		H.nrf.tx_per_event_b = ble_bpe;
		H.nrf.on_notify = ble_notify;
		if (ble_out && !(H.ble_out = fopen(ble_out, "wb")))
			die("cannot write %s: %s", ble_out, strerror(errno));
		H.spi_in = avr_io_getirq(H.avr, AVR_IOCTL_SPI_GETIRQ(0), SPI_IRQ_INPUT);
		avr_irq_t *spi_out = avr_io_getirq(H.avr, AVR_IOCTL_SPI_GETIRQ(0), SPI_IRQ_OUTPUT);
		avr_irq_t *cs = avr_io_getirq(H.avr, AVR_IOCTL_IOPORT_GETIRQ('B'), IOPORT_IRQ_PIN4);
		avr_irq_t *rst = avr_io_getirq(H.avr, AVR_IOCTL_IOPORT_GETIRQ('D'), IOPORT_IRQ_PIN4);
		H.ble_irq_pin = avr_io_getirq(H.avr, AVR_IOCTL_IOPORT_GETIRQ('E'), IOPORT_IRQ_PIN6);
		if (!H.spi_in || !spi_out || !cs || !rst || !H.ble_irq_pin)
			die("mcu %s lacks the SPI or the ports of the Feather's nRF51822", mcu);
		avr_irq_register_notify(spi_out, ble_spi_hook, NULL);
		avr_irq_register_notify(cs, ble_cs_hook, NULL);
		avr_irq_register_notify(rst, ble_rst_hook, NULL);
		H.ble_irq_level = -1;
		avr_cycle_timer_register(H.avr, freq / BLE_TICK_PER_S, ble_tick, NULL);
	}

	/* UART: no stdio echo, no usleep() on polled status reads. */
	uint32_t flags = 0;
	if (avr_ioctl(H.avr, AVR_IOCTL_UART_GET_FLAGS(uart_name), &flags))
		die("mcu %s has no UART '%c'", mcu, uart_name);
	flags &= ~(uint32_t)(AVR_UART_FLAG_POLL_SLEEP | AVR_UART_FLAG_STDIO);
	avr_ioctl(H.avr, AVR_IOCTL_UART_SET_FLAGS(uart_name), &flags);
	H.uart_in = avr_io_getirq(H.avr, AVR_IOCTL_UART_GETIRQ(uart_name), UART_IRQ_INPUT);
	H.uart = find_uart(uart_name);
	if (!H.uart && H.uart_bytes_per_s > 0)
		die("cannot find simavr's UART '%c' state for --uart-bytes-per-s", uart_name);
	H.uart_cpb = H.uart ? H.uart->cycles_per_byte : 0;
	avr_irq_register_notify(
	    avr_io_getirq(H.avr, AVR_IOCTL_UART_GETIRQ(uart_name), UART_IRQ_OUTPUT), uart_out_hook,
	    NULL);
	avr_irq_register_notify(
	    avr_io_getirq(H.avr, AVR_IOCTL_UART_GETIRQ(uart_name), UART_IRQ_OUT_XON), uart_xon_hook,
	    NULL);
	avr_irq_register_notify(
	    avr_io_getirq(H.avr, AVR_IOCTL_UART_GETIRQ(uart_name), UART_IRQ_OUT_XOFF),
	    uart_xoff_hook, NULL);

	H.out = malloc(OUT_RING_SIZE);
	pty_open(pty_link);
	printf("PTY path=%s\n", H.slave_name);

	struct sigaction sa = {.sa_handler = on_signal};
	sigaction(SIGINT, &sa, NULL);
	sigaction(SIGTERM, &sa, NULL);
	signal(SIGPIPE, SIG_IGN);

	const char *reason = "sim_time";
	if (wait_host) {
		/* Hold until the host has the pty open and has written something. */
		while (!g_signal) {
			short ev = pty_service(100);
			if (H.host_seen && H.in_len)
				break;
			if (H.host_seen && (ev & POLLHUP) && exit_on_hangup) {
				reason = "hangup";
				break;
			}
		}
		/* The wake-up byte stays queued until the firmware enables its receiver (XON). */
	}

	const uint64_t service_cycles = freq / 1000; /* pty serviced every 1 ms simulated */
	const uint64_t report_cycles = (uint64_t)(report_s * freq);
	const uint64_t limit_cycles = (uint64_t)(sim_limit_s * freq);
	uint64_t next_service = 0, next_report = report_cycles;
	double wall0 = now_wall();
	int exit_code = 0;
	printf("START sim_s=%.6f\n", sim_s());

	if (strcmp(reason, "hangup") && !g_signal) {
		for (;;) {
			int state = avr_run(H.avr);
			if (state == cpu_Done || state == cpu_Crashed) {
				reason = state == cpu_Done ? "cpu_done" : "crashed";
				exit_code = state == cpu_Crashed ? 3 : 0;
				break;
			}
			if (H.avr->cycle < next_service)
				continue;
			next_service = H.avr->cycle + service_cycles;

			uart_police();
			short ev = pty_service(0);
			if (H.host_seen && (ev & POLLHUP) && exit_on_hangup) {
				reason = "hangup";
				break;
			}
			if (H.out_len > max_backlog) { /* host behind: pause the simulated world */
				double p0 = now_wall();
				H.pauses++;
				while (H.out_len > max_backlog / 2 && !g_signal) {
					ev = pty_service(100);
					if (ev & POLLHUP)
						break;
				}
				H.pause_wall_s += now_wall() - p0;
			}
			for (int i = 0; i < H.n_watch; i++) {
				watch_t *w = &H.watch[i];
				int v = H.avr->data[w->addr];
				if (v != w->last) {
					printf("REG sim_s=%.6f name=%s addr=0x%04x value=%d\n", sim_s(), w->name,
					       w->addr, v);
					w->last = v;
				}
			}
			if (speed > 0) {
				double ahead = sim_s() / speed - (now_wall() - wall0);
				if (ahead > 0.002) {
					struct timespec ts = {(time_t)ahead, (long)(fmod(ahead, 1.0) * 1e9)};
					nanosleep(&ts, NULL);
				}
			}
			if (H.avr->cycle >= next_report) {
				next_report += report_cycles;
				double wall = now_wall() - wall0;
				printf("TIME sim_s=%.6f wall_s=%.3f speed=%.2f cycles=%llu\n", sim_s(), wall,
				       wall > 0 ? sim_s() / wall : 0.0, (unsigned long long)H.avr->cycle);
			}
			if (g_signal) {
				reason = "signal";
				break;
			}
			if (limit_cycles && H.avr->cycle >= limit_cycles)
				break;
		}
	} else if (g_signal) {
		reason = "signal";
	}
	double wall = now_wall() - wall0;
	printf("EXIT reason=%s sim_s=%.6f wall_s=%.3f speed=%.2f tx_bytes=%llu rx_bytes=%llu "
	       "pauses=%llu pause_wall_s=%.3f discarded=%llu\n",
	       reason, sim_s(), wall, wall > 0 ? sim_s() / wall : 0.0,
	       (unsigned long long)H.tx_bytes, (unsigned long long)H.rx_bytes,
	       (unsigned long long)H.pauses, H.pause_wall_s, (unsigned long long)H.discarded);
	if (H.ble) {
		if (H.ble_out)
			fflush(H.ble_out);
		printf("BLE sim_s=%.6f event=summary connected=%d central_bytes=%llu spi_bytes=%llu "
		       "cs_falls=%llu cs_low_us=%.0f cs_low_max_us=%.1f commands=%u packets_in=%u packets_out=%u not_ready=%u "
		       "overreads=%u tx_errors=%u protocol_errors=%u cmd_errors=%u\n",
		       sim_s(), H.nrf.connected, (unsigned long long)H.ble_rx_bytes,
		       (unsigned long long)H.spi_bytes, (unsigned long long)H.cs_falls,
		       H.cs_low_cycles * 1e6 / H.avr->frequency, H.cs_low_max_cycles * 1e6 / H.avr->frequency,
		       H.nrf.commands, H.nrf.packets_in, H.nrf.packets_out, H.nrf.not_ready,
		       H.nrf.overreads, H.nrf.tx_errors, H.nrf.protocol_errors, H.nrf.cmd_errors);
	}
	/* Linger with the pty open so that the host can read what the firmware already sent
	   (closing the master would discard it): until the host hangs up, or --linger expires. */
	for (double t0 = now_wall(); H.host_seen && now_wall() - t0 < linger_s;)
		if (pty_service(50) & POLLHUP)
			break;
	if (pty_link)
		unlink(pty_link);
	avr_terminate(H.avr);
	return exit_code;
}
