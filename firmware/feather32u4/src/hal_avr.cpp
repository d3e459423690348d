// hal_avr.cpp -- ATmega32u4 glue (see hal_avr.h). Register names from the ATmega32u4 datasheet.
#include "hal_avr.h"

#include <avr/eeprom.h>
#include <avr/interrupt.h>
#include <avr/wdt.h>

#include "../config.h"
#include "core/cdc_write.h"
#include "core/frame.h"
#include "core/oversample.h"

namespace stipi {

static_assert(STIPI_PIN_LOADCELL == A0, "load cell pin must be A0 (config.h)");
static_assert(STIPI_PIN_VBAT == A9, "VBAT pin must be A9 (config.h)");
static_assert(STIPI_PIN_SUPPLY5 < 0 || (STIPI_PIN_SUPPLY5 >= A0 && STIPI_PIN_SUPPLY5 <= A11),
              "STIPI_PIN_SUPPLY5 must be an analog pin or -1 (config.h)");
static_assert(STIPI_PIN_LED_PWM == 5, "LED PWM is wired to OC3A = D5 (config.h)");
static_assert(F_CPU == 8000000L, "Timer1 setup assumes 8 MHz (prescaler 8 -> 1 us ticks)");

Sampler g_sampler;

namespace {

enum AdcState : uint8_t { kAdcIdle = 0, kAdcSample = 1, kAdcSupply = 2 };

volatile uint8_t g_adc_state = kAdcIdle;
volatile uint32_t g_sample_t_us = 0;
volatile bool g_supply_wanted = false;
volatile uint16_t g_supply_raw = 0;
volatile uint16_t g_sum = 0;        // conversions of the current sample, summed (<= 16 * 1023)
volatile uint8_t g_conv_left = 0;   // conversions still to take for the current sample
uint8_t g_log2n = 0;                // 2^g_log2n conversions per sample (set with the timer)
uint16_t g_center_us = 0;           // timer instant -> middle of its conversions [us]
volatile uint16_t g_gain_q14 = kGainOne;  // ratiometric supply correction (oversample.h)
volatile bool g_corrected = false;
uint8_t g_loadcell_channel = 0;
uint8_t g_supply_channel = 0;       // STIPI_PIN_SUPPLY5 when wired, else VBAT (A9)

// Select an ADC channel (0..15: MUX5 lives in ADCSRB) with AVcc as reference.
inline void adc_select(uint8_t channel) {
  ADCSRB = static_cast<uint8_t>((ADCSRB & ~_BV(MUX5)) | (((channel >> 3) & 1) << MUX5));
  ADMUX = static_cast<uint8_t>(_BV(REFS0) | (channel & 0x07));
}

inline void adc_start() { ADCSRA |= _BV(ADSC) | _BV(ADIE); }

}  // namespace

uint8_t irq_save() {
  const uint8_t s = SREG;
  cli();
  return s;
}

void irq_restore(uint8_t state) { SREG = state; }

}  // namespace stipi

using namespace stipi;

// Sample instant: note the time and start the first of 2^g_log2n conversions (ADC clock
// 125 kHz: 104 us each); the ADC interrupt chains the others back to back.
ISR(TIMER1_COMPA_vect) {
  const uint32_t t = micros();
  if (g_adc_state != kAdcIdle) {
    g_sampler.isr_drop();  // previous conversions still running: this sample is lost, counted
    return;
  }
  g_sample_t_us = t + g_center_us;  // the mean stands for the middle of the conversions
  g_sum = 0;
  g_conv_left = static_cast<uint8_t>(1u << g_log2n);
  g_adc_state = kAdcSample;
  adc_start();
}

ISR(ADC_vect) {
  const uint16_t value = ADC;
  if (g_adc_state == kAdcSample) {
    g_sum = static_cast<uint16_t>(g_sum + value);
    if (--g_conv_left != 0) {
      adc_start();  // next conversion of this sample, right away
      return;
    }
    g_sampler.isr_push(oversample_output(g_sum, g_log2n, g_gain_q14), g_sample_t_us);
    // Timer1 (CTC, 1 us ticks) counts from this sample's instant; the supply reading is chained
    // only if it lands before the next one (oversample.h), else it waits for a later sample.
    if (g_supply_wanted &&
        supply_fits(static_cast<uint16_t>(TCNT1 + 1u), static_cast<uint16_t>(OCR1A + 1u),
                    (TIFR1 & _BV(OCF1A)) != 0)) {
      adc_select(g_supply_channel);  // chain the supply reading right after the sample
      g_adc_state = kAdcSupply;
      adc_start();
      return;
    }
  } else if (g_adc_state == kAdcSupply) {
    g_supply_raw = value;
    g_supply_wanted = false;
#if STIPI_PIN_SUPPLY5 >= 0
    uint16_t gain;
    g_corrected = supply_gain_q14(value, &gain);  // once per heartbeat: one division
    g_gain_q14 = gain;
#endif
    adc_select(g_loadcell_channel);
  }
  g_adc_state = kAdcIdle;
}

namespace stipi {

// ---- reset cause and watchdog -------------------------------------------------------------
// MCUSR says why the MCU reset, but the Feather's Caterina bootloader clears it before the
// sketch runs (Caterina.c: "MCUSR = 0"). So two marks in .noinit RAM (not cleared at start-up)
// stand in: kRamKept survives any reset but not a power loss; kWatchdogMarked is written by the
// watchdog interrupt one period before the watchdog's reset. core/frame.h infer_reset_cause().

namespace {
const uint32_t kRamKept = 0x53545031UL;  // "STP1"
const uint8_t kWatchdogMarked = 0xA5;
uint32_t g_ram_mark __attribute__((section(".noinit")));
uint8_t g_watchdog_mark __attribute__((section(".noinit")));
uint8_t g_mcusr_at_start __attribute__((section(".noinit")));
#if STIPI_WATCHDOG
const uint8_t kOurPrescaler = WDTO_500MS;  // STIPI_WATCHDOG_PERIOD_MS
static_assert(STIPI_WATCHDOG_PERIOD_MS == 500, "kOurPrescaler is WDTO_500MS");
const uint8_t kPrescalerBits = _BV(WDP3) | _BV(WDP2) | _BV(WDP1) | _BV(WDP0);

void watchdog_arm() {  // interrupt + reset mode (ATmega32u4 datasheet 10.9.2)
  IrqGuard guard;
  wdt_reset();
  WDTCSR = _BV(WDCE) | _BV(WDE);
  WDTCSR = static_cast<uint8_t>(_BV(WDIE) | _BV(WDE) | (kOurPrescaler & 0x07) |
                                ((kOurPrescaler & 0x08) ? _BV(WDP3) : 0));
}
#endif
}  // namespace

// Before the C runtime sets up RAM (.init3): read and clear MCUSR and stop a watchdog left
// running by a watchdog reset (avr-libc <avr/wdt.h>: WDRF keeps it enabled).
extern "C" void stipi_save_mcusr() __attribute__((naked, used, section(".init3")));
extern "C" void stipi_save_mcusr() {
  g_mcusr_at_start = MCUSR;
  MCUSR = 0;
  wdt_disable();
}

ISR(WDT_vect) { g_watchdog_mark = kWatchdogMarked; }  // the reset follows one period later

void AvrBoard::begin_watchdog() {
  reset_cause_ = infer_reset_cause(g_mcusr_at_start, g_ram_mark == kRamKept,
                                   g_watchdog_mark == kWatchdogMarked);
  g_ram_mark = kRamKept;
  g_watchdog_mark = 0;
#if STIPI_WATCHDOG
  watchdog_arm();
#endif
}

void AvrBoard::kick_watchdog() {
#if STIPI_WATCHDOG
  const uint8_t w = WDTCSR;
  if (!(w & _BV(WDE))) {  // switched off (e.g. a bootloader touch the core cancelled)
    watchdog_arm();
    return;
  }
  // The core's 1200-baud touch set its own 120 ms reset (CDC.cpp): let it happen.
  const uint8_t ours = static_cast<uint8_t>((kOurPrescaler & 0x07) |
                                            ((kOurPrescaler & 0x08) ? _BV(WDP3) : 0));
  if ((w & kPrescalerBits) != ours) return;
  wdt_reset();
  if (!(w & _BV(WDIE))) {  // the interrupt fired but the loop came back in time
    g_watchdog_mark = 0;
    WDTCSR = static_cast<uint8_t>(w | _BV(WDIE));
  }
#endif
}

void AvrBoard::begin() {
  g_loadcell_channel = analogPinToChannel(STIPI_PIN_LOADCELL - A0);
#if STIPI_PIN_SUPPLY5 >= 0
  g_supply_channel = analogPinToChannel(STIPI_PIN_SUPPLY5 - A0);
#else
  g_supply_channel = analogPinToChannel(STIPI_PIN_VBAT - A0);
#endif
  adc_select(g_loadcell_channel);  // init() already enabled the ADC at F_CPU/64 = 125 kHz
  // LED: Timer3 fast PWM 8-bit (WGM3 = 0101), no prescaler -> 8 MHz / 256 = 31.25 kHz on OC3A.
  pinMode(STIPI_PIN_LED_PWM, OUTPUT);
  digitalWrite(STIPI_PIN_LED_PWM, LOW);
  TCCR3A = _BV(WGM30);
  TCCR3B = _BV(WGM32) | _BV(CS30);
  OCR3A = 0;
  // The first supply reading, taken now with the ADC otherwise idle.
  g_supply_wanted = true;
  request_supply_measurement();
}

void AvrBoard::start_sampling(uint16_t period_us) {
  IrqGuard guard;
  TCCR1A = 0;
  TCCR1B = 0;
  TCNT1 = 0;
  g_log2n = oversample_log2(period_us);
  g_center_us = oversample_center_us(g_log2n);
  OCR1A = static_cast<uint16_t>(period_us - 1);  // CTC: period = (OCR1A + 1) ticks of 1 us
  TIFR1 = _BV(OCF1A);
  TIMSK1 |= _BV(OCIE1A);
  TCCR1B = _BV(WGM12) | _BV(CS11);  // CTC on OCR1A, clk/8 = 1 MHz
}

void AvrBoard::stop_sampling() {
  {
    IrqGuard guard;
    TCCR1B = 0;
    TIMSK1 &= static_cast<uint8_t>(~_BV(OCIE1A));
  }
  // Let in-flight conversions land (at most 16 + 1 supply, ~1.8 ms), bounded.
  const uint32_t start = micros();
  while (g_adc_state != kAdcIdle && micros() - start < 2500) {
  }
}

void AvrBoard::set_led(uint8_t level) {
  IrqGuard guard;
  if (level == 0 || level == 255) {
    TCCR3A = _BV(WGM30);  // disconnect OC3A: a steady level, no 1-tick spikes
    digitalWrite(STIPI_PIN_LED_PWM, level ? HIGH : LOW);
  } else {
    OCR3A = level;
    TCCR3A = _BV(COM3A1) | _BV(WGM30);
  }
}

void AvrBoard::request_supply_measurement() {
  IrqGuard guard;
  g_supply_wanted = true;
  // While sampling, the ADC interrupt chains the reading after the next sample; otherwise
  // start it now.
  if ((TIMSK1 & _BV(OCIE1A)) == 0 && g_adc_state == kAdcIdle) {
    adc_select(g_supply_channel);
    g_adc_state = kAdcSupply;
    adc_start();
  }
}

uint16_t AvrBoard::supply_mv() {
  uint16_t raw;
  {
    IrqGuard guard;
    raw = g_supply_raw;
  }
#if STIPI_PIN_SUPPLY5 >= 0
  return static_cast<uint16_t>(supply5_mv_of_raw(raw));
#else
  return static_cast<uint16_t>((static_cast<uint32_t>(raw) * STIPI_VBAT_DIVIDER * STIPI_ADC_REF_MV) >>
                               STIPI_ADC_BITS);
#endif
}

bool AvrBoard::supply_corrected() {
  IrqGuard guard;
  return g_corrected;
}

// ---- SPI to the nRF51822 ------------------------------------------------------------------

void AvrSpiPort::begin() {
  digitalWrite(STIPI_PIN_BLE_CS, HIGH);
  pinMode(STIPI_PIN_BLE_CS, OUTPUT);
  pinMode(STIPI_PIN_BLE_IRQ, INPUT);
  digitalWrite(STIPI_PIN_BLE_RST, HIGH);
  pinMode(STIPI_PIN_BLE_RST, OUTPUT);
  // SS (PB0) must be an output for master mode; SCK (PB1) and MOSI (PB2) outputs.
  DDRB |= _BV(PB0) | _BV(PB1) | _BV(PB2);
  PORTB |= _BV(PB0);
  // Master, mode 0, MSB first, F_CPU/4 = 2 MHz (module maximum is 4 MHz).
  SPCR = _BV(SPE) | _BV(MSTR);
  SPSR = 0;
}

void AvrSpiPort::select(bool active) { digitalWrite(STIPI_PIN_BLE_CS, active ? LOW : HIGH); }

uint8_t AvrSpiPort::transfer(uint8_t out) {
  SPDR = out;
  // 8 bits at 2 MHz = 32 CPU cycles; bounded so a missing/odd SPI model cannot hang the loop.
  for (uint16_t spin = 0; spin < 2000 && !(SPSR & _BV(SPIF)); ++spin) {
  }
  return SPDR;
}

bool AvrSpiPort::irq() { return digitalRead(STIPI_PIN_BLE_IRQ) == HIGH; }

void AvrSpiPort::reset(bool asserted) { digitalWrite(STIPI_PIN_BLE_RST, asserted ? LOW : HIGH); }

// ---- EEPROM -------------------------------------------------------------------------------

uint8_t AvrEeprom::read(uint16_t addr) {
  return eeprom_read_byte(reinterpret_cast<const uint8_t*>(addr));
}

void AvrEeprom::write(uint16_t addr, uint8_t value) {
  eeprom_update_byte(reinterpret_cast<uint8_t*>(addr), value);
}

// ---- links --------------------------------------------------------------------------------

// Not `(bool)Serial`: the Arduino core's Serial_::operator bool() calls delay(10) every time,
// which stalled the main loop 20-30 ms per frame and overflowed the sample ring (seen in the
// simavr HIL test: ~40 % of samples dropped at 1000 Hz). DTR is what it tests, minus the delay.
bool UsbCdcLink::is_open() { return USBDevice.configured() && Serial.dtr(); }

int16_t UsbCdcLink::read() { return static_cast<int16_t>(Serial.read()); }

namespace {
// The Arduino core's Serial (USB CDC) for core/cdc_write.h: at most room - 1 bytes with the
// SOF interrupt (which flushes the bank, USBCore.cpp USB_Flush) held off, so USB_Send never
// waits for the other bank and never fails after queuing (tests/firmware/usb_core_model).
struct AvrCdc {
  uint8_t sofe = 0;
  void hold_sof(bool hold) {
    IrqGuard guard;  // UDIEN is also written by the core's USB interrupt
    if (hold) {
      sofe = UDIEN & _BV(SOFE);
      UDIEN &= static_cast<uint8_t>(~_BV(SOFE));
    } else {
      UDIEN |= sofe;
    }
  }
  int available_for_write() { return Serial.availableForWrite(); }
  size_t write(const uint8_t* data, uint16_t n) { return Serial.write(data, n); }
};

struct CdcWriter {
  uint16_t operator()(const uint8_t* data, uint16_t n) {
    AvrCdc cdc;
    return cdc_write(cdc, data, n);
  }
};
}  // namespace

bool UsbCdcLink::write_frame(const uint8_t* data, uint8_t len) {
  if (!is_open()) return false;
  const bool queued = queue_.push(data, len);
  service();
  return queued;
}

void UsbCdcLink::service() {
  if (queue_.count() == 0 || !is_open()) return;
  CdcWriter writer;
  queue_.drain(writer);
}

int16_t Uart1Link::read() { return static_cast<int16_t>(Serial1.read()); }

namespace {
struct Uart1Writer {
  uint16_t operator()(const uint8_t* data, uint16_t n) {
    const int room = Serial1.availableForWrite();
    if (room <= 0) return 0;
    const uint16_t k = n < static_cast<uint16_t>(room) ? n : static_cast<uint16_t>(room);
    return static_cast<uint16_t>(Serial1.write(data, k));  // fits the TX buffer: no wait
  }
};
}  // namespace

bool Uart1Link::write_frame(const uint8_t* data, uint8_t len) {
  const bool queued = queue_.push(data, len);
  service();
  return queued;
}

void Uart1Link::service() {
  if (queue_.count() == 0) return;
  Uart1Writer writer;
  queue_.drain(writer);
}

}  // namespace stipi
