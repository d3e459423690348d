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

// nRF51822 running the Bluefruit SDEP firmware, as an SPI slave (see test_sdep.cpp for the
// behaviour it models: 0xFE until CS has been held 100 us, responses queued behind IRQ).
class FakeNrf51 : public stipi::SpiPort {
 public:
  explicit FakeNrf51(FakeClock& clock) : clock_(clock) {}

  void select(bool active) override;
  uint8_t transfer(uint8_t out) override;
  bool irq() override { return present && !responses_.empty(); }
  void reset(bool asserted) override {
    if (asserted && !reset_asserted) ++resets;
    reset_asserted = asserted;
    if (asserted) responses_.clear();
  }

  struct Packet {
    uint8_t type;
    uint16_t id;
    bool more;
    std::vector<uint8_t> payload;
  };

  bool present = true;
  bool connected = true;
  int not_ready_transactions = 0;  // the next N transactions answer 0xFE
  int uart_tx_errors = 0;          // the next N UART TX packets get an error reply...
  int uart_tx_error_skip = 0;      // ...after this many more have been accepted
  bool reset_asserted = false;
  int resets = 0;
  int cs_too_early = 0;            // transactions that clocked before 100 us of CS setup
  std::deque<uint8_t> central_to_probe;    // written by the BLE central (served by 0x0A02)
  std::vector<uint8_t> probe_to_central;   // sent by the probe through 0x0A01
  std::vector<Packet> commands;            // every command packet received
  std::vector<std::string> at_commands;    // every complete AT command
  size_t responses_pending() const { return responses_.size(); }
  // Queue a reply of `id` carrying `data`, split into 16-byte packets with the more-data bit.
  void queue_response(uint16_t id, const std::vector<uint8_t>& data);

 private:
  void finish_command();
  FakeClock& clock_;
  std::deque<std::vector<uint8_t>> responses_;
  std::vector<uint8_t> in_;
  std::vector<uint8_t> at_buffer_;
  bool selected_ = false;
  uint32_t select_us_ = 0;
  enum Mode { kIdle, kRejected, kCommand, kRead } mode_ = kIdle;
  size_t read_pos_ = 0;
};

}  // namespace fakes

#endif
