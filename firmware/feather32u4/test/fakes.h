// fakes.h -- host stand-ins for the hardware the core talks to (clock, timer/ADC board, EEPROM,
// byte links, the nRF51822 SPI slave), and a host-side decoder for probe -> host frames.
//
// These replace hardware only; every piece of the firmware core under test is the real code.
#ifndef STIPI_TEST_FAKES_H
#define STIPI_TEST_FAKES_H

#include <cstdint>
#include <deque>
#include <functional>
#include <string>
#include <vector>

#include "../src/core/hal.h"
#include "../src/core/sampler.h"
#include "nrf51_sim.h"

namespace fakes {

// Host critical-section bookkeeping (hal.h's irq_save/irq_restore on the host).
int irq_depth();

class FakeClock : public stipi::Clock {
 public:
  explicit FakeClock(uint32_t start_us = 0) : now_us(start_us) {}
  uint32_t micros() override { return now_us; }
  void delay_us(uint16_t us) override { now_us += us; }
  uint32_t now_us;
};

// Timer1 + ADC: while sampling, one sample per period, pushed into the real Sampler.
class FakeBoard : public stipi::Board {
 public:
  FakeBoard(FakeClock& clock, stipi::Sampler& sampler) : clock_(clock), sampler_(sampler) {}
  void start_sampling(uint16_t period_us) override {
    sampling = true;
    period = period_us;
    next_us = clock_.now_us + period_us;
    ++starts;
  }
  void stop_sampling() override {
    sampling = false;
    ++stops;
  }
  void set_led(uint8_t level) override { led = level; }
  void request_supply_measurement() override { ++supply_requests; }
  uint16_t supply_mv() override { return supply; }
  bool supply_corrected() override { return corrected; }
  // Let `us` microseconds pass, taking samples at each timer event.
  void advance(uint32_t us) {
    const uint32_t target = clock_.now_us + us;
    while (sampling && static_cast<int32_t>(target - next_us) >= 0) {
      clock_.now_us = next_us;
      sampler_.isr_push(adc(sampler_.taken()), next_us);
      next_us += period;
    }
    clock_.now_us = target;
  }

  bool sampling = false;
  uint16_t period = 0;
  uint32_t next_us = 0;
  uint8_t led = 0;
  uint16_t supply = 4123;
  bool corrected = true;  // the AVR glue without a 5 V sense answers false (flag bit 4)
  int supply_requests = 0;
  int starts = 0;
  int stops = 0;
  std::function<uint16_t(uint32_t)> adc = [](uint32_t index) {
    return static_cast<uint16_t>(index & 0x3FF);
  };

 private:
  FakeClock& clock_;
  stipi::Sampler& sampler_;
};

class FakeEeprom : public stipi::Eeprom {
 public:
  FakeEeprom() : mem(1024, 0xFF) {}
  uint8_t read(uint16_t addr) override { return mem.at(addr); }
  void write(uint16_t addr, uint8_t value) override {
    ++writes;
    if (stuck) return;  // a worn-out cell: the write does not take
    if (writes_left >= 0 && writes_left-- == 0) {
      stuck = true;  // power lost mid-record: this and later writes are lost
      return;
    }
    mem.at(addr) = value;
  }
  std::vector<uint8_t> mem;
  int writes = 0;
  int writes_left = -1;  // >= 0: only that many more writes succeed
  bool stuck = false;
};

class FakeLink : public stipi::ByteLink {
 public:
  bool is_open() override { return open; }
  int16_t read() override {
    if (rx.empty()) return -1;
    const uint8_t b = rx.front();
    rx.pop_front();
    return b;
  }
  bool write_frame(const uint8_t* data, uint8_t len) override {
    if (!accept) return false;
    tx.insert(tx.end(), data, data + len);
    return true;
  }
  void push(const std::vector<uint8_t>& bytes) { rx.insert(rx.end(), bytes.begin(), bytes.end()); }
  bool open = true;
  bool accept = true;
  std::deque<uint8_t> rx;
  std::vector<uint8_t> tx;
};

// A frame as the host sees it (decoded with a COBS decoder written separately from the core's).
struct HostFrame {
  uint8_t version;
  uint8_t type;
  uint16_t seq;
  uint32_t t_us;
  std::vector<uint8_t> body;
  bool crc_ok;
};

std::vector<uint8_t> reference_cobs_decode(const std::vector<uint8_t>& enc, bool* ok);
// Split `wire` at 0x00 delimiters and parse every non-empty frame; consumes `wire`.
std::vector<HostFrame> take_frames(std::vector<uint8_t>& wire);
// Build a COMMAND on the wire: COBS(header | cmd | args | crc) 0x00.
std::vector<uint8_t> command_wire(uint16_t seq, uint8_t cmd, const std::vector<uint8_t>& args,
                                  uint32_t t_us = 0);

// The simulated nRF51 of tests/firmware/nrf51_sim (written from Adafruit's SDEP.md, proven
// against Adafruit's own driver) behind the core's SpiPort. Every SPI byte costs 4 us of the
// given clock (8 bits at 2 MHz), so time passes -- and samples are taken -- during SDEP traffic.
class SimNrf51Port : public stipi::SpiPort {
 public:
  explicit SimNrf51Port(stipi::Clock& clock) : clock_(clock) { nrf51_sim_init(&m); }
  void sync() { nrf51_sim_advance(&m, clock_.micros()); }
  void select(bool active) override {
    sync();
    nrf51_sim_select(&m, active ? 1 : 0);
  }
  uint8_t transfer(uint8_t out) override {
    clock_.delay_us(4);
    sync();
    ++bytes;
    return nrf51_sim_xfer(&m, out);
  }
  bool irq() override {
    sync();
    return nrf51_sim_irq(&m) != 0;
  }
  void reset(bool asserted) override {
    sync();
    rst_pulses += asserted && !m.in_reset;
    nrf51_sim_reset(&m, asserted ? 1 : 0);
  }
  nrf51_sim m;
  uint64_t bytes = 0;
  uint32_t rst_pulses = 0;  // RST assertions (the module reset by the probe)

 private:
  stipi::Clock& clock_;
};

}  // namespace fakes

#endif
