// probe.h -- the probe's behaviour: links in, frames out, commands, streaming, heartbeat.
//
// Owns: the sender sequence counter, one COBS decoder per link, the command handler (ACK status
// codes of docs/protocol.md), batching ring-buffer samples into SAMPLES frames, TARE averaging,
// WRITE_CAL persistence and the STATUS heartbeat. Every frame goes to every open link (same
// bytes, same seq); commands are accepted from any link and their ACK goes to all links.
// Does not own hardware: it drives Board/Clock/Eeprom/ByteLink interfaces (hal.h).
#ifndef STIPI_CORE_PROBE_H
#define STIPI_CORE_PROBE_H

#include <stdint.h>

#include "../../config.h"
#include "cal_store.h"
#include "cobs.h"
#include "frame.h"
#include "hal.h"
#include "heartbeat.h"
#include "sampler.h"

namespace stipi {

static_assert(STIPI_BATCH_SIZE >= 1 && STIPI_BATCH_SIZE <= 24, "batch must be 1..24 samples");
static_assert(STIPI_TARE_SAMPLES == 16, "TARE averages 16 samples (docs/protocol.md)");
static_assert(STIPI_HEARTBEAT_PERIOD_US <= 1000000UL, "STATUS must be sent at least every 1 s");
static_assert(STIPI_DEFAULT_RATE_HZ >= STIPI_MIN_RATE_HZ &&
                  STIPI_DEFAULT_RATE_HZ <= STIPI_MAX_RATE_HZ, "default rate out of range");

enum LinkSlot : uint8_t { kLinkUsb = 0, kLinkUart = 1, kLinkBle = 2, kLinkCount = 3 };

// Sampling period for a rate, rounded to the nearest microsecond [us].
uint16_t period_for_rate(uint16_t rate_hz);

class Probe {
 public:
  Probe(Clock& clock, Board& board, Sampler& sampler, Eeprom& eeprom);

  void set_link(LinkSlot slot, ByteLink* link) { links_[slot] = link; }
  // Load calibration, switch the LED off, flush the host receivers with a 0x00.
  void begin();
  // One main-loop pass: read commands, send due batches and the heartbeat. Bounded time.
  void poll();

  bool streaming() const { return streaming_; }
  bool tare_pending() const { return tare_pending_; }
  uint16_t rate_hz() const { return rate_hz_; }
  uint8_t led_level() const { return led_level_; }
  const Calibration& calibration() const { return cal_; }
  bool cal_valid() const { return cal_valid_; }
  uint16_t next_seq() const { return seq_; }
  uint32_t rx_errors() const { return rx_errors_; }  // bad COBS/CRC/version/type frames
  uint32_t link_drops(LinkSlot slot) const { return link_drops_[slot]; }
  uint8_t status_flags();
  // What STATUS reports besides the probe's own state (plain values, no virtual calls: on the
  // AVR every virtual function costs RAM for its vtable entry).
  void set_reset_cause(uint8_t cause) { reset_cause_ = cause; }              // once, at start
  void set_ble_health(uint8_t state, uint16_t restarts) {                    // every pass
    ble_state_ = state;
    ble_restarts_ = restarts;
  }

 private:
  void read_link(uint8_t slot);
  void handle_command(const Command& cmd);
  void service_samples();
  void feed_tare(const Batch& batch);
  void finish_tare();
  void start_sampling();
  void stop_and_flush();
  void send_batch(const Batch& batch);
  void send_status();
  void send_ack(uint16_t ref_seq, uint8_t cmd, uint8_t status, const uint8_t* result,
                uint8_t result_len);
  void send_frame(uint8_t frame_len);

  Clock& clock_;
  Board& board_;
  Sampler& sampler_;
  CalStore cal_store_;
  Heartbeat heartbeat_;
  ByteLink* links_[kLinkCount];
  CobsDecoder decoders_[kLinkCount];
  uint32_t link_drops_[kLinkCount];
  uint8_t frame_[kMaxFrameLen];
  uint8_t wire_[kMaxWireLen];
  uint16_t seq_;
  uint32_t rx_errors_;
  Calibration cal_;
  bool cal_valid_;
  bool streaming_;
  uint16_t rate_hz_;
  uint8_t led_level_;
  uint8_t reset_cause_ = 0;
  uint8_t ble_state_ = 0;
  uint16_t ble_restarts_ = 0;
  // TARE in progress
  bool tare_pending_;
  bool tare_owns_timer_;  // sampling was started only for the tare
  uint16_t tare_ref_seq_;
  uint32_t tare_from_index_;
  uint8_t tare_count_;
  uint32_t tare_sum_;
};

}  // namespace stipi

#endif
