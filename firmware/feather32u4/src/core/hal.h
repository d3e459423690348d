// hal.h -- the small hardware interfaces the portable core talks through.
//
// Owns: the abstract clock, SPI port (with the nRF51822's CS/IRQ/RST lines), EEPROM, byte
// links and board controls (sampling timer, LED PWM, supply voltage), plus the critical-section
// hooks. Does not own any implementation: src/hal_avr.* implements them on the ATmega32u4 and
// test/fakes.h on the host (AceButton style: logic on the host, thin glue on the chip).
#ifndef STIPI_CORE_HAL_H
#define STIPI_CORE_HAL_H

#include <stdint.h>

namespace stipi {

// Monotonic microsecond clock (Arduino micros(): wraps every 2^32 us = 71.6 min) and busy wait.
class Clock {
 public:
  virtual uint32_t micros() = 0;
  virtual void delay_us(uint16_t us) = 0;
};

// SPI bus master plus the nRF51822's control lines.
class SpiPort {
 public:
  virtual void select(bool active) = 0;       // drive CS low (true) or high (false)
  virtual uint8_t transfer(uint8_t out) = 0;  // one full-duplex byte, MSB first
  virtual bool irq() = 0;                      // IRQ line high = a packet is waiting
  virtual void reset(bool asserted) = 0;       // drive RST low (true) or high (false)
};

// Byte-addressed EEPROM. write() may be slow; readback is verified by the caller.
class Eeprom {
 public:
  virtual uint8_t read(uint16_t addr) = 0;
  virtual void write(uint16_t addr, uint8_t value) = 0;
};

// A byte stream to the host (USB CDC, UART, BLE UART).
class ByteLink {
 public:
  virtual bool is_open() = 0;  // a host can currently receive
  virtual int16_t read() = 0;  // next received byte, or -1 when none
  // Queue a whole wire frame; returns false (and sends nothing) when it cannot be queued now.
  virtual bool write_frame(const uint8_t* data, uint8_t len) = 0;
  // Move queued bytes on (called every main-loop pass); must not wait.
  virtual void service() {}
};

// Board controls the probe logic needs.
class Board {
 public:
  // Start the fixed-rate sampling timer: one ADC conversion every period_us [us]; each
  // result is pushed into the Sampler from interrupt context.
  virtual void start_sampling(uint16_t period_us) = 0;
  // Stop the timer and wait until no conversion is in flight (no push after this returns).
  virtual void stop_sampling() = 0;
  virtual void set_led(uint8_t level) = 0;  // PWM duty 0..255
  virtual void request_supply_measurement() = 0;
  virtual uint16_t supply_mv() = 0;          // last measured supply voltage [mV]
  // Samples are corrected for the FC22's measured 5 V supply (ratiometric); false sets
  // STATUS.flags bit 4.
  virtual bool supply_corrected() { return false; }
};

// Critical section (interrupts off) around state shared with the sampling ISR. Defined by the
// platform glue: SREG save/cli/restore on the AVR, a nesting counter on the host.
uint8_t irq_save();
void irq_restore(uint8_t state);

class IrqGuard {
 public:
  IrqGuard() : state_(irq_save()) {}
  ~IrqGuard() { irq_restore(state_); }

 private:
  IrqGuard(const IrqGuard&);
  IrqGuard& operator=(const IrqGuard&);
  uint8_t state_;
};

}  // namespace stipi

#endif  // STIPI_CORE_HAL_H
