/*
 * Harness self-test program (not the probe firmware): samples ADC7 (A0 on the Feather 32u4,
 * AVCC reference) at 100 Hz from a Timer1 compare interrupt and prints every sample on UART1
 * (115200 8N1, U2X) as "S <index> <t_us> <adc>\n"; echoes every received byte as "E <hex>\n".
 * t_us is the Timer1 tick count (1 tick = 8 us with /64 prescaling at 8 MHz) times 8, taken at
 * the sample interrupt, so the harness's ADC timing and the UART bridge can be checked
 * without the real firmware.
 */
#include <avr/interrupt.h>
#include <avr/io.h>
#include <stdio.h>

#define RATE_HZ 100u
#define TICKS_PER_SAMPLE (F_CPU / 64u / RATE_HZ) /* 1250 */

static volatile uint32_t g_ticks_hi; /* Timer1 periods elapsed */
static volatile uint16_t g_adc;
static volatile uint32_t g_index, g_t_us;
static volatile uint8_t g_ready;

ISR(TIMER1_COMPA_vect)
{
	g_ticks_hi++;
	ADCSRA |= _BV(ADSC); /* start a conversion now: sample-and-hold at this instant */
}

ISR(ADC_vect)
{
	g_adc = ADC;
	g_t_us = (g_ticks_hi * TICKS_PER_SAMPLE) * 8u;
	g_index++;
	g_ready = 1;
}

static void uart_put(char c)
{
	while (!(UCSR1A & _BV(UDRE1)))
		;
	UDR1 = c;
}

static void uart_puts(const char *s)
{
	while (*s)
		uart_put(*s++);
}

int main(void)
{
	UCSR1A = _BV(U2X1);
	UBRR1 = 8; /* 8 MHz / (8 * 9) = 111111 baud ~ 115200 */
	UCSR1C = _BV(UCSZ11) | _BV(UCSZ10);
	UCSR1B = _BV(TXEN1) | _BV(RXEN1);

	ADMUX = _BV(REFS0) | 7;                                    /* AVCC, ADC7 */
	ADCSRA = _BV(ADEN) | _BV(ADIE) | _BV(ADPS2) | _BV(ADPS1); /* /64 -> 125 kHz */

	TCCR1A = 0;
	TCCR1B = _BV(WGM12) | _BV(CS11) | _BV(CS10); /* CTC, /64 */
	OCR1A = TICKS_PER_SAMPLE - 1;
	TIMSK1 = _BV(OCIE1A);
	sei();

	char line[48];
	for (;;) {
		if (g_ready) {
			cli();
			uint32_t idx = g_index, t = g_t_us;
			uint16_t a = g_adc;
			g_ready = 0;
			sei();
			snprintf(line, sizeof line, "S %lu %lu %u\n", (unsigned long)idx,
			         (unsigned long)t, a);
			uart_puts(line);
		}
		if (UCSR1A & _BV(RXC1)) {
			snprintf(line, sizeof line, "E %02x\n", UDR1);
			uart_puts(line);
		}
	}
}
