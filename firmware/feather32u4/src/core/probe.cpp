// probe.cpp -- main-loop behaviour of the probe (see probe.h).
#include "probe.h"

namespace stipi {

uint16_t period_for_rate(uint16_t rate_hz) {
  return static_cast<uint16_t>((1000000UL + rate_hz / 2) / rate_hz);
}

Probe::Probe(Clock& clock, Board& board, Sampler& sampler, Eeprom& eeprom)
    : clock_(clock), board_(board), sampler_(sampler),
      cal_store_(eeprom, STIPI_EEPROM_CAL_ADDR), heartbeat_(STIPI_HEARTBEAT_PERIOD_US), seq_(0),
      rx_errors_(0), cal_valid_(false), streaming_(false), rate_hz_(STIPI_DEFAULT_RATE_HZ),
      led_level_(0), tare_pending_(false), tare_owns_timer_(false), tare_ref_seq_(0),
      tare_from_index_(0), tare_count_(0), tare_sum_(0) {
  for (uint8_t i = 0; i < kLinkCount; ++i) {
    links_[i] = 0;
    link_drops_[i] = 0;
  }
  cal_.zero_counts = 0;
  cal_.span_un_per_count = 0;
}

void Probe::begin() {
  cal_valid_ = cal_store_.load(cal_) && cal_.span_un_per_count != 0;
  board_.set_led(led_level_);
  sampler_.set_period(period_for_rate(rate_hz_));
  const uint8_t zero = 0;
  for (uint8_t i = 0; i < kLinkCount; ++i) {
    if (links_[i] && links_[i]->is_open()) links_[i]->write_frame(&zero, 1);
  }
}

uint8_t Probe::status_flags() {
  uint8_t flags = 0;
  if (streaming_) flags |= kFlagStreaming;
  if (links_[kLinkBle] && links_[kLinkBle]->is_open()) flags |= kFlagBleConnected;
  if (links_[kLinkUsb] && links_[kLinkUsb]->is_open()) flags |= kFlagUsbOpen;
  if (cal_valid_) flags |= kFlagCalValid;
  if (!board_.supply_corrected()) flags |= kFlagSupplyUncorrected;
  return flags;
}

void Probe::poll() {
  for (uint8_t i = 0; i < kLinkCount; ++i) {
    if (!links_[i]) continue;
    links_[i]->service();
    read_link(i);
  }
  service_samples();
  const uint32_t now = clock_.micros();
  if (heartbeat_.due(now)) {
    board_.request_supply_measurement();
    send_status();
    heartbeat_.sent(now);
  }
}

void Probe::read_link(uint8_t slot) {
  for (uint8_t n = 0; n < STIPI_LINK_READ_BUDGET; ++n) {
    const int16_t b = links_[slot]->read();
    if (b < 0) return;
    const CobsDecoder::Result r = decoders_[slot].feed(static_cast<uint8_t>(b));
    if (r == CobsDecoder::kError || r == CobsDecoder::kOverlong) {
      ++rx_errors_;
    } else if (r == CobsDecoder::kFrame) {
      Command cmd;
      if (decode_command(decoders_[slot].data(), decoders_[slot].length(), cmd) == kDecodeOk) {
        handle_command(cmd);
      } else {
        ++rx_errors_;
      }
    }
  }
}

void Probe::start_sampling() {
  sampler_.set_period(period_for_rate(rate_hz_));
  board_.start_sampling(sampler_.period_us());
}

void Probe::stop_and_flush() {
  board_.stop_sampling();
  Batch b;
  while (sampler_.pop(b, STIPI_BATCH_SIZE) > 0) send_batch(b);
}

void Probe::handle_command(const Command& c) {
  // Commands that change sampling wait while a TARE owns the sample stream.
  const bool blocked_by_tare = tare_pending_;
  uint8_t status = kAckOk;
  switch (c.cmd) {
    case kCmdStreamStart:
      if (c.arg_len != 0) {
        status = kAckBadArgument;
      } else if (blocked_by_tare) {
        status = kAckBusy;
      } else if (!streaming_) {
        start_sampling();
        streaming_ = true;
      }
      break;
    case kCmdStreamStop:
      if (c.arg_len != 0) {
        status = kAckBadArgument;
      } else if (blocked_by_tare) {
        status = kAckBusy;
      } else if (streaming_) {
        stop_and_flush();
        streaming_ = false;
      }
      break;
    case kCmdSetRate: {
      const uint16_t rate = c.arg_len == 2 ? get_u16(c.args) : 0;
      if (c.arg_len != 2 || rate < STIPI_MIN_RATE_HZ || rate > STIPI_MAX_RATE_HZ) {
        status = kAckBadArgument;
      } else if (blocked_by_tare) {
        status = kAckBusy;
      } else {
        // Samples taken at the old period leave in their own batches before the change.
        if (streaming_) stop_and_flush();
        rate_hz_ = rate;
        if (streaming_) {
          start_sampling();
        } else {
          sampler_.set_period(period_for_rate(rate_hz_));
        }
      }
      break;
    }
    case kCmdSetLed:
      if (c.arg_len != 1) {
        status = kAckBadArgument;
      } else {
        led_level_ = c.args[0];
        board_.set_led(led_level_);
      }
      break;
    case kCmdTare:
      if (c.arg_len != 0) {
        status = kAckBadArgument;
      } else if (tare_pending_) {
        status = kAckBusy;
      } else {
        tare_pending_ = true;
        tare_ref_seq_ = c.seq;
        tare_count_ = 0;
        tare_sum_ = 0;
        tare_from_index_ = sampler_.taken();  // "the next 16 samples": none already queued
        tare_owns_timer_ = !streaming_;
        if (tare_owns_timer_) start_sampling();
        return;  // answered when the 16th sample arrives (finish_tare)
      }
      break;
    case kCmdWriteCal: {
      if (c.arg_len != 6) {
        status = kAckBadArgument;
        break;
      }
      Calibration cal;
      cal.zero_counts = get_u16(c.args);
      cal.span_un_per_count = static_cast<int32_t>(get_u32(c.args + 2));
      const uint16_t adc_max = (1u << STIPI_ADC_OUT_BITS) - 1;
      if (cal.zero_counts > adc_max || cal.span_un_per_count == 0) {
        status = kAckBadArgument;
      } else if (blocked_by_tare) {
        status = kAckBusy;
      } else if (!cal_store_.store(cal)) {
        status = kAckEepromFailed;
      } else {
        cal_ = cal;
        cal_valid_ = true;
      }
      break;
    }
    case kCmdGetInfo: {
      if (c.arg_len != 0) {
        status = kAckBadArgument;
        break;
      }
      uint8_t r[15];
      r[0] = kProtocolVersion;
      r[1] = STIPI_FW_MAJOR;
      r[2] = STIPI_FW_MINOR;
      r[3] = STIPI_FW_PATCH;
      put_u16(r + 4, rate_hz_);
      r[6] = led_level_;
      put_u16(r + 7, cal_.zero_counts);
      put_u32(r + 9, static_cast<uint32_t>(cal_.span_un_per_count));
      r[13] = STIPI_ADC_OUT_BITS;
      r[14] = STIPI_BATCH_SIZE;
      send_ack(c.seq, c.cmd, kAckOk, r, 15);
      return;
    }
    default:
      status = kAckUnknownCommand;
      break;
  }
  send_ack(c.seq, c.cmd, status, 0, 0);
}

void Probe::service_samples() {
  if (!streaming_ && !tare_pending_) return;
  // While streaming only whole batches leave (partial ones on stop/rate change, and while the
  // ring overflows, since it takes samples again only once it is empty); a tare alone consumes
  // whatever arrived. At most 4 pops per pass keep commands and heartbeat responsive.
  Batch b;
  for (uint8_t k = 0; k < 4; ++k) {
    const uint8_t want = streaming_ && !sampler_.overflowing() ? STIPI_BATCH_SIZE : 1;
    if (sampler_.available() < want) break;
    sampler_.pop(b, streaming_ ? STIPI_BATCH_SIZE : STIPI_TARE_SAMPLES);
    if (tare_pending_) feed_tare(b);
    if (streaming_) send_batch(b);
  }
}

void Probe::feed_tare(const Batch& b) {
  for (uint8_t i = 0; i < b.count && tare_count_ < STIPI_TARE_SAMPLES; ++i) {
    const uint32_t index = b.first_index + i;
    if (static_cast<int32_t>(index - tare_from_index_) < 0) continue;  // taken before TARE
    tare_sum_ += b.adc[i];
    ++tare_count_;
  }
  if (tare_count_ == STIPI_TARE_SAMPLES) finish_tare();
}

void Probe::finish_tare() {
  tare_pending_ = false;
  if (tare_owns_timer_) {
    board_.stop_sampling();
    sampler_.clear();  // the tare's own samples are not streamed
    tare_owns_timer_ = false;
  }
  Calibration cal = cal_;
  cal.zero_counts = static_cast<uint16_t>((tare_sum_ + STIPI_TARE_SAMPLES / 2) / STIPI_TARE_SAMPLES);
  if (!cal_store_.store(cal)) {
    send_ack(tare_ref_seq_, kCmdTare, kAckEepromFailed, 0, 0);
    return;
  }
  cal_ = cal;
  cal_valid_ = cal_.span_un_per_count != 0;
  uint8_t r[2];
  put_u16(r, cal_.zero_counts);
  send_ack(tare_ref_seq_, kCmdTare, kAckOk, r, 2);
}

void Probe::send_batch(const Batch& b) {
  send_frame(encode_samples(frame_, seq_, b.t_us, b.first_index, b.period_us, b.adc, b.count));
}

void Probe::send_status() {
  StatusBody s;
  s.led_level = led_level_;
  s.rate_hz = rate_hz_;
  s.dropped = sampler_.dropped();
  s.supply_mv = board_.supply_mv();
  s.flags = status_flags();
  s.ble_state = ble_state_;
  s.ble_restarts = ble_restarts_;
  s.reset_cause = reset_cause_;
  send_frame(encode_status(frame_, seq_, clock_.micros(), s));
}

void Probe::send_ack(uint16_t ref_seq, uint8_t cmd, uint8_t status, const uint8_t* result,
                     uint8_t result_len) {
  send_frame(encode_ack(frame_, seq_, clock_.micros(), ref_seq, cmd, status, result, result_len));
}

void Probe::send_frame(uint8_t frame_len) {
  if (frame_len == 0) return;
  const uint8_t n = wire_encode(frame_, frame_len, wire_);
  for (uint8_t i = 0; i < kLinkCount; ++i) {
    ByteLink* link = links_[i];
    if (!link || !link->is_open()) continue;
    if (!link->write_frame(wire_, n)) ++link_drops_[i];
  }
  ++seq_;
}

}  // namespace stipi
