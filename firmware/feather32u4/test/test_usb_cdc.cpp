// test_usb_cdc.cpp -- the USB CDC writer (src/core/cdc_write.h) against a model of the Arduino
// core's USB code (tests/firmware/usb_core_model, written from USBCore.cpp and CDC.cpp): frames
// at a sampling rate go through the real TxQueue and the writer into the model while the host
// reads in bursts or stops; the host decodes what it got. The writer must never make USB_Send
// wait (its 250 ms delay(1) loop) nor fail after queuing bytes (which made the old writer send
// them twice), and every loss must be a whole frame the ring refused, seen as an exact gap.
#include <cstdio>
#include <functional>
#include <utility>
#include <vector>

#include "../src/core/cdc_write.h"
#include "../src/core/crc16.h"
#include "../src/core/frame.h"
#include "../src/core/tx_queue.h"
#include "fakes.h"
#include "runner.h"
#include "usb_core_model.h"

using namespace stipi;

namespace {
// What hal_avr.cpp's glue does with Serial and UDIEN.SOFE, on the model.
struct ModelCdc {
  usbmodel::UsbCdcModel& m;
  void hold_sof(bool hold) { m.set_sofe(!hold); }
  int available_for_write() { return m.available_for_write(); }
  size_t write(const uint8_t* d, uint16_t n) { return m.write(d, n); }
};

// The writer before: all the room availableForWrite() reports, SOF not held.
uint16_t old_cdc_write(usbmodel::UsbCdcModel& m, const uint8_t* data, uint16_t n) {
  const int room = m.available_for_write();
  if (room <= 0) return 0;
  const uint16_t k = n < static_cast<uint16_t>(room) ? n : static_cast<uint16_t>(room);
  return static_cast<uint16_t>(m.write(data, k));
}

struct Decoded {
  uint32_t frames = 0, bad = 0, samples = 0, gaps = 0, lost = 0, seq_repeats = 0;
};

// Split at 0x00, COBS-decode, check the CRC; SAMPLES first_index continuity.
Decoded decode(const std::vector<uint8_t>& wire) {
  Decoded d;
  std::vector<uint8_t> cur;
  bool started = false;
  uint32_t next_index = 0;
  int last_seq = -1;
  for (uint8_t b : wire) {
    if (b != 0) {
      cur.push_back(b);
      continue;
    }
    if (cur.empty()) continue;
    bool ok = false;
    const std::vector<uint8_t> f = fakes::reference_cobs_decode(cur, &ok);
    cur.clear();
    if (!ok || f.size() < 10 ||
        crc16(f.data(), static_cast<uint16_t>(f.size() - 2)) !=
            static_cast<uint16_t>(f[f.size() - 2] | f[f.size() - 1] << 8)) {
      ++d.bad;
      continue;
    }
    ++d.frames;
    const int seq = f[2] | f[3] << 8;
    if (seq == last_seq) ++d.seq_repeats;
    last_seq = seq;
    if (f[1] != kMsgSamples) continue;
    const uint32_t first = f[8] | f[9] << 8 | f[10] << 16 | static_cast<uint32_t>(f[11]) << 24;
    if (started && first != next_index) {
      ++d.gaps;
      d.lost += first - next_index;
    }
    started = true;
    next_index = first + f[14];
    d.samples += f[14];
  }
  return d;
}

struct Run {
  uint32_t taken = 0, ring_lost = 0, longest_pass_us = 0;
  Decoded host;
  usbmodel::UsbCdcModel model;
};

// `seconds` of batches of 10 samples at rate_hz plus a 26-byte STATUS every 0.5 s, one main
// loop pass every 250 us of model time, the writer called each pass as UsbCdcLink does.
void stream(Run& r, uint16_t rate_hz, uint32_t seconds, bool old_writer) {
  TxQueue<STIPI_USB_TX_RING> queue;
  ModelCdc cdc{r.model};
  const uint32_t batch_us = 10u * 1000000u / rate_hz;
  uint32_t next_batch_us = batch_us, next_status_us = 500000;
  uint16_t seq = 0;
  uint16_t adc[10] = {100, 101, 102, 103, 104, 105, 106, 107, 108, 109};
  uint8_t frame[kMaxFrameLen], wire[kMaxWireLen];
  const uint32_t end_us = seconds * 1000000u;
  while (r.model.now_us < end_us) {
    const uint32_t t0 = r.model.now_us;
    if (static_cast<int32_t>(t0 - next_batch_us) >= 0) {
      const uint8_t n = encode_samples(frame, seq++, t0, r.taken,
                                       static_cast<uint16_t>(1000000u / rate_hz), adc, 10);
      if (!queue.push(wire, wire_encode(frame, n, wire))) r.ring_lost += 10;
      r.taken += 10;
      next_batch_us += batch_us;
    }
    if (static_cast<int32_t>(t0 - next_status_us) >= 0) {
      StatusBody s = {0, rate_hz, 0, 5000, 0, 3, 0, 1};
      const uint8_t n = encode_status(frame, seq++, t0, s);
      queue.push(wire, wire_encode(frame, n, wire));  // a lost STATUS is a seq gap only
      next_status_us += 500000;
    }
    if (old_writer) {
      while (queue.count() > 0) {
        uint16_t n = 0;
        const uint8_t* p = queue.front(&n);
        const uint16_t took = old_cdc_write(r.model, p, n);
        if (took == 0) break;
        queue.pop(took);
      }
    } else {
      auto write = [&cdc](const uint8_t* p, uint16_t n) { return cdc_write(cdc, p, n); };
      queue.drain(write);
    }
    r.model.cpu_us(250);
    if (r.model.now_us - t0 > r.longest_pass_us) r.longest_pass_us = r.model.now_us - t0;
  }
  r.model.host_reads = [](uint32_t) { return true; };  // the host catches up at the end
  for (int i = 0; i < 200; ++i) {
    if (old_writer) break;
    auto write = [&cdc](const uint8_t* p, uint16_t n) { return cdc_write(cdc, p, n); };
    queue.drain(write);
    r.model.cpu_us(1000);
  }
  r.host = decode(r.model.received);
}

// The host takes one packet in 1 ms frame of every 20 (its driver polls in bursts: up to 64 B
// per read, 3.2 kB/s) for 1 s, then stops for 2 s (an application that stops reading), etc.
bool bursts_then_stops(uint32_t ms) { return ms % 3000 < 1000 && ms % 20 == 0; }

void check_never_waits_nor_repeats(const Run& r) {
  CHECK_EQ(r.model.wait_ms, 0u);        // USB_Send never entered its delay(1) loop
  CHECK_EQ(r.model.send_failures, 0u);  // never returned -1
  CHECK_EQ(r.host.bad, 0u);             // no byte sent twice, none missing inside a frame
  CHECK_EQ(r.host.seq_repeats, 0u);
  CHECK(r.longest_pass_us <= 400u);
}
}  // namespace

TEST(usb_cdc_200hz_host_reading_in_bursts_loses_nothing) {
  // Reads 1 ms then pauses: continuously (0), in bursts (19 ms), and 10 ms then 240 ms.
  const std::pair<uint32_t, uint32_t> patterns[] = {{1, 0}, {1, 19}, {10, 240}};
  for (const std::pair<uint32_t, uint32_t>& rp : patterns) {
    Run r;
    const uint32_t read_ms = rp.first, period_ms = rp.first + rp.second;
    r.model.host_reads = [=](uint32_t ms) { return ms % period_ms < read_ms; };
    stream(r, 200, 20, false);
    std::printf("usb cdc 200 Hz, host reads %u ms of every %u: taken %u, host %u, "
                "ring lost %u, USB_Send waits %u ms\n",
                read_ms, period_ms, r.taken, r.host.samples, r.ring_lost, r.model.wait_ms);
    check_never_waits_nor_repeats(r);
    CHECK_EQ(r.ring_lost, 0u);
    CHECK_EQ(r.host.samples, r.taken);
    CHECK_EQ(r.host.gaps, 0u);
  }
}

TEST(usb_cdc_host_that_stops_reading_loses_whole_frames_counted_exactly) {
  for (uint16_t rate_hz : {uint16_t{200}, uint16_t{1000}}) {
    Run r;
    r.model.host_reads = bursts_then_stops;
    stream(r, rate_hz, 10, false);  // ends in a reading second: every loss is followed by data
    std::printf("usb cdc %u Hz, host reads in bursts 1 s, stops 2 s: taken %u, host %u, "
                "ring lost %u (gaps %u, %u samples), USB_Send waits %u ms\n",
                rate_hz, r.taken, r.host.samples, r.ring_lost, r.host.gaps, r.host.lost,
                r.model.wait_ms);
    check_never_waits_nor_repeats(r);
    CHECK(r.ring_lost > 0u);
    CHECK_EQ(r.host.lost, r.ring_lost);  // every loss is a gap of exactly that size
    CHECK_EQ(r.host.samples + r.host.lost, r.taken);
  }
}

TEST(usb_model_reproduces_the_old_writers_stall_and_repeats) {
  // The model is not on our side: the writer this replaces, on the same model and host,
  // stalls the loop for ~250 ms and sends queued bytes twice (the failure seen on the bench).
  Run r;
  r.model.host_reads = bursts_then_stops;
  stream(r, 1000, 10, true);
  std::printf("usb cdc old writer, 1000 Hz, host reads in bursts 1 s, stops 2 s: waited %u "
              "ms, failed %u times (%u after queuing), %u bad frames, longest pass %u us\n",
              r.model.wait_ms, r.model.send_failures, r.model.failed_after_queuing, r.host.bad,
              r.longest_pass_us);
  CHECK(r.model.wait_ms >= 249u);
  CHECK(r.model.failed_after_queuing > 0u);
  CHECK(r.host.bad + r.host.seq_repeats > 0u);
  CHECK(r.longest_pass_us >= 249000u);
}
