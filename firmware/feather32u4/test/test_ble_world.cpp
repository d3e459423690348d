// test_ble_world.cpp -- the real probe core + BLE link against the simulated nRF51 with a
// central, in simulated time: samples are taken by the fake timer while SDEP traffic runs
// (every SPI byte and CS setup advances the clock), USB and UART take everything, and the
// central reads at its connection-interval rate. Prints the figures docs/firmware.md quotes:
//   make -C firmware/feather32u4 host-test | grep 'ble world'
#include <cstdio>
#include <string>
#include <utility>
#include <vector>

#include "../src/core/frame.h"
#include "../src/core/probe.h"
#include "../src/core/sdep.h"
#include "fakes.h"
#include "runner.h"

using namespace stipi;

namespace {
// Clock whose waits let the sampling timer fire (the ISR preempts busy waits on the chip).
class WorldClock : public Clock {
 public:
  explicit WorldClock(fakes::FakeBoard& board, fakes::FakeClock& c) : board_(board), c_(c) {}
  uint32_t micros() override { return c_.now_us; }
  void delay_us(uint16_t us) override { board_.advance(us); }

 private:
  fakes::FakeBoard& board_;
  fakes::FakeClock& c_;
};

struct Stream {
  uint32_t samples = 0, gaps = 0, lost = 0, frames = 0;
  uint32_t next_index = 0;
  bool started = false;
  std::vector<std::pair<uint32_t, uint8_t>> batches;  // (first_index, count) as received
  std::vector<uint8_t> last_status;                    // body of the latest STATUS
  uint16_t next_seq = 0;
  uint32_t seq_gaps_after_last_batch = 0;  // frames lost after the newest SAMPLES received
  void feed(std::vector<uint8_t>& wire) {
    for (const fakes::HostFrame& f : fakes::take_frames(wire)) {
      if (f.crc_ok && f.type == kMsgStatus) last_status = f.body;
      if (f.crc_ok && frames > 0 && f.seq != next_seq) ++seq_gaps_after_last_batch;
      if (f.crc_ok) next_seq = static_cast<uint16_t>(f.seq + 1);
      if (!f.crc_ok || f.type != kMsgSamples) continue;
      ++frames;
      seq_gaps_after_last_batch = 0;
      const uint32_t first = f.body[0] | f.body[1] << 8 | f.body[2] << 16 |
                             static_cast<uint32_t>(f.body[3]) << 24;
      if (started && first != next_index) {
        ++gaps;
        lost += first - next_index;
      }
      started = true;
      next_index = first + f.body[6];
      samples += f.body[6];
      batches.emplace_back(first, f.body[6]);
    }
  }
};

struct World {
  fakes::FakeClock clock;
  Sampler sampler;
  fakes::FakeBoard board{clock, sampler};
  WorldClock wclock{board, clock};
  fakes::FakeEeprom eeprom;
  Probe probe{wclock, board, sampler, eeprom};
  fakes::SimNrf51Port port{wclock};
  SdepDriver sdep{port, wclock};
  BleUartLink ble{sdep, port, wclock};
  fakes::FakeLink usb, uart;
  std::vector<uint8_t> central;
  Stream s_usb, s_uart, s_ble;
  uint32_t max_pass_us = 0;

  World(uint32_t interval_us, uint16_t bytes_per_event) {
    port.m.conn_interval_us = interval_us;
    port.m.tx_per_event_b = bytes_per_event;
    port.m.process_us = 5000;
    port.m.on_notify = [](void* ctx, const uint8_t* d, uint16_t n) {
      static_cast<World*>(ctx)->central.insert(static_cast<World*>(ctx)->central.end(), d, d + n);
    };
    port.m.notify_ctx = this;
    nrf51_sim_set_connected(&port.m, 1);
    probe.set_link(kLinkUsb, &usb);
    probe.set_link(kLinkUart, &uart);
    probe.set_link(kLinkBle, &ble);
    ble.begin();
    probe.begin();
  }
  // Main loop: each pass costs its SPI time plus 100 us of other work.
  void run(uint32_t us) {
    const uint32_t end = clock.now_us + us;
    while (static_cast<int32_t>(end - clock.now_us) > 0) {
      const uint32_t t0 = clock.now_us;
      ble.poll();
      probe.set_ble_health(ble.health(), ble.module_resets());
      probe.poll();
      board.advance(100);
      port.sync();
      if (clock.now_us - t0 > max_pass_us) max_pass_us = clock.now_us - t0;
      s_usb.feed(usb.tx);
      s_uart.feed(uart.tx);
      s_ble.feed(central);
    }
  }
  void command(uint16_t seq, uint8_t cmd, const std::vector<uint8_t>& args) {
    usb.push(fakes::command_wire(seq, cmd, args));
  }
};

struct Result {
  uint32_t taken, usb, uart, ble, ble_gaps, ble_lost, dropped, frames_lost, link_drops, max_pass;
  uint32_t room_waits, module_tx_errors, discarded, stale;
};

Result stream(uint16_t rate_hz, uint32_t interval_us, uint16_t bytes_per_event, const char* name,
              uint32_t process_us = 5000, bool old_module_firmware = false) {
  World w(interval_us, bytes_per_event);
  w.port.m.process_us = process_us;
  w.port.m.no_fifo_command = old_module_firmware ? 1 : 0;
  w.run(STIPI_BLE_BOOT_US + 200000 + 4 * process_us);  // reset, ATE=0, AT+GAPGETCONN
  CHECK(w.ble.is_open());
  w.command(1, kCmdSetRate, {static_cast<uint8_t>(rate_hz), static_cast<uint8_t>(rate_hz >> 8)});
  w.command(2, kCmdStreamStart, {});
  const uint32_t first = w.sampler.taken();
  w.run(60000000);  // 60 s simulated
  w.command(3, kCmdStreamStop, {});
  w.run(6000000);   // the BLE backlog (module FIFO 1 KB at 400 B/s, and the ring) drains
  Result r;
  r.taken = w.sampler.taken() - first;
  r.usb = w.s_usb.samples;
  r.uart = w.s_uart.samples;
  r.ble = w.s_ble.samples;
  r.ble_gaps = w.s_ble.gaps;
  r.ble_lost = w.s_ble.lost;
  // Batches lost after the last one the central got show as a seq gap on a later STATUS.
  const uint32_t trailing = first + r.taken - w.s_ble.next_index;
  if (trailing > 0) {
    CHECK(w.s_ble.seq_gaps_after_last_batch > 0);
    r.ble_lost += trailing;
  }
  r.dropped = w.sampler.dropped();
  r.frames_lost = w.ble.frames_lost();
  r.link_drops = w.probe.link_drops(kLinkBle);
  r.max_pass = w.max_pass_us;
  r.room_waits = w.port.m.room_waits;
  r.module_tx_errors = w.port.m.tx_errors;
  r.discarded = w.port.m.unread_at_command;
  r.stale = w.ble.stale_answers();
  std::printf(
      "ble world %s: %u Hz 60 s, central %u B per %u us, module %u ms per command: taken %u, "
      "usb %u, uart %u, ble %u (%u gaps, %u samples missing; %u frames refused by the full "
      "module, %u not queued), dropped %u, BLE %.0f samples/s, longest loop pass %u us; "
      "module waited for room %u times, %u answers discarded unread, %u read stale\n",
      name, rate_hz, bytes_per_event, interval_us, process_us / 1000, r.taken, r.usb, r.uart,
      r.ble, r.ble_gaps, r.ble_lost, r.frames_lost, r.link_drops, r.dropped, r.ble / 60.0,
      r.max_pass, r.room_waits, r.discarded, r.stale);
  return r;
}

void check_lossless_wired(const Result& r) {
  CHECK_EQ(r.dropped, 0u);
  CHECK_EQ(r.usb, r.taken);
  CHECK_EQ(r.uart, r.taken);
  CHECK(r.max_pass <= 1000);
}
}  // namespace

TEST(ble_world_100hz_central_keeps_up) {
  const Result r = stream(100, 30000, 20, "central");  // 1 notification per 30 ms: 667 B/s
  check_lossless_wired(r);
  CHECK_EQ(r.ble, r.taken);  // within budget: nothing lost on BLE either
  CHECK_EQ(r.ble_gaps, 0u);
}

TEST(ble_world_100hz_slow_central_losses_are_counted_gaps) {
  const Result r = stream(100, 50000, 20, "slow central");  // 400 B/s < 434 B/s needed
  check_lossless_wired(r);
  CHECK(r.ble < r.taken);
  CHECK(r.ble_gaps >= 1u);
  // Every missing sample is in a gap the host sees (first_index jumps), none silently.
  CHECK_EQ(r.ble + r.ble_lost, r.taken);
  // Flow control from the module's FIFO room (AT+BLEUARTFIFO=TX): no TX waits for room or is
  // refused; what BLE cannot carry stays out of the module (the ring refuses whole frames).
  CHECK_EQ(r.room_waits, 0u);
  CHECK_EQ(r.module_tx_errors, 0u);
  CHECK_EQ(r.frames_lost, 0u);
  CHECK(r.link_drops > 0u);
}

TEST(ble_world_slow_module_answers_are_never_abandoned) {
  // A module taking 60-120 ms per command (the old 250 ms timeout left 50 ms over its 200 ms
  // wait): no command times out, no answer is left unread or read stale, BLE loses only what
  // the central cannot take, in exact gaps.
  for (uint32_t process_us : {60000u, 120000u}) {
    const Result r = stream(100, 50000, 20, "slow module", process_us);
    check_lossless_wired(r);
    CHECK_EQ(r.ble + r.ble_lost, r.taken);
    CHECK_EQ(r.discarded, 0u);
    CHECK_EQ(r.stale, 0u);
    CHECK_EQ(r.room_waits, 0u);
    CHECK_EQ(r.module_tx_errors, 0u);
  }
}

TEST(ble_world_module_without_fifo_command_falls_back_to_its_errors) {
  // Bluefruit firmware before 0.6.7 answers ERROR to AT+BLEUARTFIFO: TX as before, the
  // module's 200 ms ERROR when full loses whole frames, still counted in exact gaps.
  const Result r = stream(100, 50000, 20, "old module firmware", 5000, true);
  check_lossless_wired(r);
  CHECK_EQ(r.ble + r.ble_lost, r.taken);
  CHECK(r.room_waits > 0u);
  CHECK(r.frames_lost > 0u);
}

TEST(ble_world_250hz_reports_what_ble_sustains) {
  const Result r = stream(250, 30000, 20, "250 Hz");
  check_lossless_wired(r);
  CHECK_EQ(r.ble + r.ble_lost, r.taken);
  const Result f = stream(250, 15000, 80, "250 Hz fast central");  // 4 notifications / 15 ms
  check_lossless_wired(f);
  CHECK_EQ(f.ble, f.taken);
}

namespace {
// Samples the central got with index >= `from`, and whether they are all consecutive.
struct After {
  uint32_t samples = 0, gaps = 0;
};
After received_after(const Stream& s, uint32_t from) {
  After a;
  uint32_t next = from;
  for (const std::pair<uint32_t, uint8_t>& b : s.batches) {
    const uint32_t first = b.first, end = b.first + b.second;
    if (end <= from) continue;
    if (first > next) ++a.gaps;  // samples between next and first never arrived
    a.samples += end - (first > from ? first : from);
    next = end;
  }
  return a;
}
}  // namespace

TEST(ble_world_slow_booting_module_gets_every_sample) {
  // 1.6 s of 0xFE after reset used to end the BLE link for the whole run (0 of 2,000).
  World w(15000, 80);  // 4 notifications per 15 ms: BLE keeps up with 200 Hz
  w.port.m.boot_us = 1600000;
  w.ble.begin();  // reset it again with the slow boot
  w.command(1, kCmdSetRate, {200, 0});
  w.command(2, kCmdStreamStart, {});
  for (int i = 0; i < 40; ++i) {  // 4 s: never counted absent on the way
    w.run(100000);
    CHECK(w.ble.state() != BleUartLink::kAbsent);
  }
  CHECK_EQ(w.port.rst_pulses, 1u);
  CHECK(w.ble.is_open());
  const uint32_t from = w.sampler.taken();  // every sample from here on must reach the central
  w.run(10000000);
  w.command(3, kCmdStreamStop, {});
  w.run(3000000);
  const uint32_t taken = w.sampler.taken() - from;
  const After a = received_after(w.s_ble, from);
  std::printf("ble world slow boot 1.6 s: 200 Hz, %u samples taken after the link came up, "
              "%u at the central, %u gaps\n", taken, a.samples, a.gaps);
  CHECK(taken >= 1990u);
  CHECK_EQ(a.samples, taken);
  CHECK_EQ(a.gaps, 0u);
  CHECK_EQ(w.sampler.dropped(), 0u);
  CHECK(w.max_pass_us <= 1000);
}

TEST(ble_world_module_restarting_mid_stream_gets_every_later_sample) {
  World w(15000, 80);  // 4 notifications per 15 ms: BLE keeps up with 200 Hz
  w.run(STIPI_BLE_BOOT_US + 200000);
  CHECK(w.ble.is_open());
  w.command(1, kCmdSetRate, {200, 0});
  w.command(2, kCmdStreamStart, {});
  w.run(5000000);
  nrf51_sim_reset(&w.port.m, 1);  // the module restarts by itself; its central drops
  nrf51_sim_set_connected(&w.port.m, 0);
  w.port.m.boot_us = 1600000;
  nrf51_sim_reset(&w.port.m, 0);
  const uint32_t restart_index = w.sampler.taken();
  w.run(1600000);
  nrf51_sim_set_connected(&w.port.m, 1);  // and reconnects once it advertises again
  w.run(3000000);  // the probe sees the restart and probes the module again
  CHECK(w.ble.is_open());
  const uint32_t from = w.sampler.taken();
  w.run(10000000);
  w.command(3, kCmdStreamStop, {});
  w.run(3000000);
  const uint32_t taken = w.sampler.taken() - from;
  const After a = received_after(w.s_ble, from);
  std::printf("ble world module restart: 200 Hz, restart at sample %u, %u samples taken after "
              "the link was back, %u at the central, %u gaps, %u module resets seen; usb %u "
              "uart %u of %u\n", restart_index, taken, a.samples, a.gaps,
              w.ble.module_resets(), w.s_usb.samples, w.s_uart.samples, w.sampler.taken());
  CHECK_EQ(w.ble.module_resets(), 1u);
  // STATUS tells the host: BLE up again, one module restart seen.
  CHECK_EQ(w.s_usb.last_status.size(), 14u);
  CHECK_EQ(w.s_usb.last_status[10], kBleUp);
  CHECK_EQ(w.s_usb.last_status[11] | w.s_usb.last_status[12] << 8, 1);
  CHECK(taken >= 1990u);
  CHECK_EQ(a.samples, taken);
  CHECK_EQ(a.gaps, 0u);
  CHECK_EQ(w.sampler.dropped(), 0u);
  CHECK_EQ(w.s_usb.gaps, 0u);
  CHECK_EQ(w.s_uart.gaps, 0u);
  CHECK(w.max_pass_us <= 1000);
}
