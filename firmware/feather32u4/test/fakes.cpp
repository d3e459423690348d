// fakes.cpp -- host fakes (see fakes.h) and the host side of irq_save/irq_restore.
#include "fakes.h"

#include <stdexcept>

#include "../src/core/crc16.h"
#include "../src/core/frame.h"
#include "../src/core/sdep.h"

namespace {
int g_irq_depth = 0;
}

namespace stipi {
uint8_t irq_save() {
  ++g_irq_depth;
  return 0;
}
void irq_restore(uint8_t) { --g_irq_depth; }
}  // namespace stipi

namespace fakes {

int irq_depth() { return g_irq_depth; }

std::vector<uint8_t> reference_cobs_decode(const std::vector<uint8_t>& enc, bool* ok) {
  std::vector<uint8_t> out;
  *ok = true;
  size_t i = 0;
  while (i < enc.size()) {
    const uint8_t code = enc[i++];
    if (code == 0) {
      *ok = false;
      return out;
    }
    for (uint8_t k = 1; k < code; ++k) {
      if (i >= enc.size()) {
        *ok = false;
        return out;
      }
      out.push_back(enc[i++]);
    }
    if (code != 0xFF && i < enc.size()) out.push_back(0);
  }
  return out;
}

std::vector<HostFrame> take_frames(std::vector<uint8_t>& wire) {
  std::vector<HostFrame> frames;
  std::vector<uint8_t> cur;
  size_t consumed = 0;
  for (size_t i = 0; i < wire.size(); ++i) {
    if (wire[i] != 0) {
      cur.push_back(wire[i]);
      continue;
    }
    consumed = i + 1;
    if (cur.empty()) continue;
    bool ok = false;
    const std::vector<uint8_t> f = reference_cobs_decode(cur, &ok);
    cur.clear();
    if (!ok || f.size() < 10) throw std::runtime_error("undecodable frame from the probe");
    HostFrame h;
    h.version = f[0];
    h.type = f[1];
    h.seq = static_cast<uint16_t>(f[2] | f[3] << 8);
    h.t_us = static_cast<uint32_t>(f[4] | f[5] << 8 | f[6] << 16 | static_cast<uint32_t>(f[7]) << 24);
    h.body.assign(f.begin() + 8, f.end() - 2);
    const uint16_t crc = static_cast<uint16_t>(f[f.size() - 2] | f[f.size() - 1] << 8);
    h.crc_ok = crc == stipi::crc16(f.data(), static_cast<uint16_t>(f.size() - 2));
    frames.push_back(h);
  }
  wire.erase(wire.begin(), wire.begin() + static_cast<long>(consumed));
  return frames;
}

std::vector<uint8_t> command_wire(uint16_t seq, uint8_t cmd, const std::vector<uint8_t>& args,
                                  uint32_t t_us) {
  std::vector<uint8_t> body;
  body.push_back(cmd);
  body.insert(body.end(), args.begin(), args.end());
  uint8_t frame[stipi::kMaxFrameLen];
  const uint8_t n = stipi::encode_frame(frame, stipi::kMsgCommand, seq, t_us, body.data(),
                                        static_cast<uint8_t>(body.size()));
  uint8_t wire[stipi::kMaxWireLen];
  const uint8_t w = stipi::wire_encode(frame, n, wire);
  return std::vector<uint8_t>(wire, wire + w);
}

// ---- FakeNrf51 ---------------------------------------------------------------------------

void FakeNrf51::queue_response(uint16_t id, const std::vector<uint8_t>& data) {
  size_t off = 0;
  do {
    const size_t n = std::min<size_t>(16, data.size() - off);
    const bool more = off + n < data.size();
    std::vector<uint8_t> p = {stipi::kSdepResponse, static_cast<uint8_t>(id),
                              static_cast<uint8_t>(id >> 8),
                              static_cast<uint8_t>(n | (more ? 0x80 : 0))};
    p.insert(p.end(), data.begin() + static_cast<long>(off), data.begin() + static_cast<long>(off + n));
    responses_.push_back(p);
    off += n;
  } while (off < data.size());
}

void FakeNrf51::select(bool active) {
  if (active && !selected_) {
    selected_ = true;
    select_us_ = clock_.now_us;
    mode_ = kIdle;
    in_.clear();
    read_pos_ = 0;
    return;
  }
  if (!active && selected_) {
    selected_ = false;
    if (mode_ == kCommand) finish_command();
    if (mode_ == kRead && read_pos_ >= 4) responses_.pop_front();
    mode_ = kIdle;
  }
}

uint8_t FakeNrf51::transfer(uint8_t out) {
  if (!present || !selected_ || reset_asserted) return 0xFF;
  if (mode_ == kRejected) return stipi::kSdepNotReady;
  if (mode_ == kIdle) {
    if (static_cast<uint32_t>(clock_.now_us - select_us_) < 100) {
      ++cs_too_early;
      mode_ = kRejected;
      return stipi::kSdepNotReady;
    }
    if (not_ready_transactions > 0) {
      --not_ready_transactions;
      mode_ = kRejected;
      return stipi::kSdepNotReady;
    }
    if (out == stipi::kSdepCommand) {
      mode_ = kCommand;
      in_.push_back(out);
      return 0xFF;
    }
    if (responses_.empty()) return stipi::kSdepNoData;
    mode_ = kRead;
  }
  if (mode_ == kCommand) {
    in_.push_back(out);
    return 0xFF;
  }
  const std::vector<uint8_t>& p = responses_.front();
  return read_pos_ < p.size() ? p[read_pos_++] : stipi::kSdepNoData;
}

void FakeNrf51::finish_command() {
  if (in_.size() < 4) return;
  Packet p;
  p.type = in_[0];
  p.id = static_cast<uint16_t>(in_[1] | in_[2] << 8);
  p.more = (in_[3] & 0x80) != 0;
  const size_t len = in_[3] & 0x1F;
  if (len > 16 || in_.size() != 4 + len) {
    responses_.push_back({stipi::kSdepError, 0x03, 0x00, 0x00});  // invalid payload
    return;
  }
  p.payload.assign(in_.begin() + 4, in_.end());
  commands.push_back(p);
  switch (p.id) {
    case stipi::kSdepCmdInitialize:
      responses_.clear();
      at_buffer_.clear();
      break;  // no response
    case stipi::kSdepCmdAtWrapper: {
      at_buffer_.insert(at_buffer_.end(), p.payload.begin(), p.payload.end());
      if (p.more) break;
      const std::string cmd(at_buffer_.begin(), at_buffer_.end());
      at_buffer_.clear();
      at_commands.push_back(cmd);
      std::string reply;
      if (cmd == "AT") {
        reply = "OK\r\n";
      } else if (cmd == "AT+GAPGETCONN") {
        reply = connected ? "1\r\nOK\r\n" : "0\r\nOK\r\n";
      } else if (cmd == "ATI") {
        reply = "BLEFRIEND32\r\nnRF51822 QFACA10\r\n0.7.7\r\nS110 8.0.0\r\nOK\r\n";
      } else {
        reply = "ERROR\r\n";
      }
      queue_response(p.id, std::vector<uint8_t>(reply.begin(), reply.end()));
      break;
    }
    case stipi::kSdepCmdUartTx:
      if (uart_tx_errors > 0 && uart_tx_error_skip > 0) {
        --uart_tx_error_skip;
      } else if (uart_tx_errors > 0) {
        --uart_tx_errors;
        responses_.push_back({stipi::kSdepError, 0x03, 0x00, 0x00});
        break;
      }
      probe_to_central.insert(probe_to_central.end(), p.payload.begin(), p.payload.end());
      queue_response(p.id, {});
      break;
    case stipi::kSdepCmdUartRx: {
      std::vector<uint8_t> data;
      while (!central_to_probe.empty() && data.size() < 40) {
        data.push_back(central_to_probe.front());
        central_to_probe.pop_front();
      }
      queue_response(p.id, data);
      break;
    }
    default:
      responses_.push_back({stipi::kSdepError, 0x01, 0x00, 0x00});  // invalid command id
      break;
  }
}

}  // namespace fakes
