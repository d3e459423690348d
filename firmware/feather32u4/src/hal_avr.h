// hal_avr.h -- ATmega32u4 implementations of the core's hardware interfaces (src/core/hal.h).
//
// Owns: Timer1 (CTC, 1 us ticks) triggering one ADC conversion per sample period, the ADC
// interrupt chain (load cell, then VBAT when asked), Timer3 fast PWM for the LEDs, the SPI
// master and nRF51822 pins, EEPROM access and the three links (USB CDC `Serial`, `Serial1`,
// BLE). Does not own any protocol logic (src/core/).
#ifndef STIPI_HAL_AVR_H
#define STIPI_HAL_AVR_H

#include <Arduino.h>

#include "core/hal.h"
#include "core/sampler.h"
#include "core/tx_queue.h"
#include "../config.h"

namespace stipi {

// The sampler filled by the ADC interrupt (defined in hal_avr.cpp).
extern Sampler g_sampler;

class AvrClock : public Clock {
 public:
  uint32_t micros() override { return ::micros(); }
  void delay_us(uint16_t us) override { delayMicroseconds(us); }
};

class AvrBoard : public Board {
 public:
  void begin();  // ADC channel, LED PWM, pins
  void start_sampling(uint16_t period_us) override;
  void stop_sampling() override;
  void set_led(uint8_t level) override;
  void request_supply_measurement() override;
  uint16_t supply_mv() override;
  bool supply_corrected() override;
  uint8_t reset_cause() const { return reset_cause_; }
  // Start the watchdog (interrupt, then reset; STIPI_WATCHDOG_PERIOD_MS) and note why the MCU
  // started. Call once from setup().
  void begin_watchdog();
  // Every main-loop pass: restart the watchdog's period. Leaves alone a watchdog the Arduino
  // core armed for the bootloader (the 1200-baud touch), so that reset still happens.
  void kick_watchdog();

 private:
  uint8_t reset_cause_ = 0;
};

class AvrSpiPort : public SpiPort {
 public:
  void begin();
  void select(bool active) override;
  uint8_t transfer(uint8_t out) override;
  bool irq() override;
  void reset(bool asserted) override;
};

class AvrEeprom : public Eeprom {
 public:
  uint8_t read(uint16_t addr) override;
  void write(uint16_t addr, uint8_t value) override;
};

// USB CDC: open while the host holds DTR; never blocks. Frames go through a ring
// (STIPI_USB_TX_RING) and leave in pieces of whatever room the endpoint bank has, so a frame
// larger than the space left waits and is split, never dropped; only a host that stops reading
// for long enough to fill the ring loses frames (seq gaps).
class UsbCdcLink : public ByteLink {
 public:
  bool is_open() override;
  int16_t read() override;
  bool write_frame(const uint8_t* data, uint8_t len) override;
  void service() override;

 private:
  TxQueue<STIPI_USB_TX_RING> queue_;
};

// Serial1 at STIPI_UART1_BAUD: always open; never waits. Frames queue whole in a ring
// (STIPI_UART1_TX_RING) and each pass writes only what Serial1.availableForWrite() says fits
// its 64-byte TX buffer; a frame finding the ring full is lost on this link (a seq gap).
class Uart1Link : public ByteLink {
 public:
  bool is_open() override { return true; }
  int16_t read() override;
  bool write_frame(const uint8_t* data, uint8_t len) override;
  void service() override;

 private:
  TxQueue<STIPI_UART1_TX_RING> queue_;
};

}  // namespace stipi

#endif
