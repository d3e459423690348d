// sdep.cpp -- SDEP driver and non-blocking Bluefruit BLE UART link (see sdep.h).
#include "sdep.h"

#include <string.h>

namespace stipi {

static_assert(STIPI_BLE_TX_CHUNK >= 80 && STIPI_BLE_TX_CHUNK <= STIPI_BLE_TX_RING,
              "a UART TX command must hold the longest wire frame (kMaxWireLen)");

void SdepDriver::begin_transaction() {
  spi_.select(true);
  clock_.delay_us(STIPI_SDEP_CS_SETUP_US);  // SDEP.md "SPI Bus Hardware Requirements"
}

SdepStatus SdepDriver::send_packet(uint16_t id, const uint8_t* payload, uint8_t len, bool more) {
  if (len > kSdepMaxPayload) return kSdepBadPacket;
  begin_transaction();
  if (spi_.transfer(kSdepCommand) == kSdepNotReady) {  // busy: the packet was not taken
    ++not_ready_;
    spi_.select(false);
    return kSdepAgain;
  }
  spi_.transfer(static_cast<uint8_t>(id));
  spi_.transfer(static_cast<uint8_t>(id >> 8));
  spi_.transfer(static_cast<uint8_t>(len | (more ? kSdepMoreData : 0)));
  for (uint8_t i = 0; i < len; ++i) spi_.transfer(payload[i]);
  spi_.select(false);
  return kSdepOk;
}

SdepStatus SdepDriver::read_packet(SdepPacket& out) {
  if (!spi_.irq()) return kSdepAgain;
  begin_transaction();
  const uint8_t type = spi_.transfer(kSdepNoData);
  // 0xFE: still processing; 0xFF: IRQ was still high after the last packet (SDEP.md "IRQ Pin").
  if (type == kSdepNotReady || type == kSdepNoData) {
    if (type == kSdepNotReady) ++not_ready_;
    spi_.select(false);
    return kSdepAgain;
  }
  const uint8_t b1 = spi_.transfer(kSdepNoData);
  const uint8_t b2 = spi_.transfer(kSdepNoData);
  const uint8_t b3 = spi_.transfer(kSdepNoData);
  out.type = type;
  out.id = static_cast<uint16_t>(b1 | (static_cast<uint16_t>(b2) << 8));
  out.more = (b3 & kSdepMoreData) != 0;
  out.len = static_cast<uint8_t>(b3 & 0x1F);
  SdepStatus st = kSdepOk;
  if (type == kSdepError) {
    out.len = 0;
    out.more = false;
    st = kSdepErrorReply;
  } else if ((type != kSdepResponse && type != kSdepAlert) || out.len > kSdepMaxPayload) {
    st = kSdepBadPacket;
  } else {
    for (uint8_t i = 0; i < out.len; ++i) out.payload[i] = spi_.transfer(kSdepNoData);
  }
  spi_.select(false);
  return st;
}

// ------------------------------------------------------------------------------------------

namespace {
const char kAtEchoOff[] = "ATE=0";  // also the boot probe: echo is on after every reset
const char kAtGetConn[] = "AT+GAPGETCONN";
const char kAtFifoTx[] = "AT+BLEUARTFIFO=TX";  // "<free bytes>\r\nOK\r\n" (firmware 0.6.7 on)
}  // namespace

BleUartLink::BleUartLink(SdepDriver& sdep, SpiPort& spi, Clock& clock)
    : sdep_(sdep), spi_(spi), clock_(clock), state_(kReset), connected_(false), attempts_(0),
      silent_(0), module_resets_(0), busy_mark_(0), since_us_(0),
      backoff_us_(STIPI_BLE_RETRY_MIN_US), last_fifo_poll_us_(0), fifo_room_(0),
      fifo_supported_(true), last_conn_poll_us_(0), last_rx_poll_us_(0), tx_failures_(0),
      stale_answers_(0), frames_lost_(0), job_(kJobNone), last_job_(kJobNone), awaiting_(false),
      failed_(false), job_id_(0), job_len_(0), job_sent_(0), job_start_us_(0), job_text_(0), reply_len_(0), tx_head_(0),
      tx_count_(0), rx_head_(0), rx_count_(0) {}

void BleUartLink::begin() {
  spi_.select(false);
  spi_.reset(true);
  since_us_ = clock_.micros();
  state_ = kReset;
  connected_ = false;
  attempts_ = 0;
  job_ = kJobNone;
}

BleHealth BleUartLink::health() const {
  if (state_ == kReady) return kBleUp;
  return state_ == kAbsent ? kBleAbsent : kBleBooting;
}

// RST released: the module boots; it may answer 0xFE for a while after STIPI_BLE_BOOT_US.
void BleUartLink::start_boot(uint32_t now) {
  since_us_ = now;
  attempts_ = 0;
  silent_ = 0;
  state_ = kBooting;
}

void BleUartLink::poll() {
  const uint32_t now = clock_.micros();
  if (state_ == kAbsent) {  // back-off over: reset the module and look again, forever
    if (static_cast<uint32_t>(now - since_us_) < backoff_us_) return;
    backoff_us_ = backoff_us_ >= STIPI_BLE_RETRY_MAX_US / 2 ? STIPI_BLE_RETRY_MAX_US
                                                             : backoff_us_ * 2;
    spi_.reset(true);
    since_us_ = now;
    state_ = kReset;
  }
  if (state_ == kReset) {
    if (static_cast<uint32_t>(now - since_us_) < STIPI_BLE_RESET_PULSE_US) return;
    spi_.reset(false);
    start_boot(now);
  }
  if (state_ == kBooting) {
    if (static_cast<uint32_t>(now - since_us_) < STIPI_BLE_BOOT_US) return;
    state_ = kProbing;
  }
  for (uint8_t k = 0; k < STIPI_SDEP_PACKETS_PER_POLL; ++k) {
    if (job_ == kJobNone) {
      if (state_ == kProbing) {
        job_text_ = kAtEchoOff;
        start_job(kJobEcho, kSdepCmdAtWrapper, sizeof(kAtEchoOff) - 1);
      } else if (state_ == kReady) {
        choose_job(now);
      }
    }
    if (job_ == kJobNone) return;
    step();
  }
}

void BleUartLink::choose_job(uint32_t now) {
  if (static_cast<uint32_t>(now - last_conn_poll_us_) >= STIPI_BLE_CONN_POLL_US) {
    last_conn_poll_us_ = now;
    job_text_ = kAtGetConn;
    start_job(kJobConn, kSdepCmdAtWrapper, sizeof(kAtGetConn) - 1);
  } else if (connected_ && rx_count_ == 0 && !(tx_count_ > 0 && last_job_ == kJobRx) &&
             static_cast<uint32_t>(now - last_rx_poll_us_) >= STIPI_BLE_RX_POLL_US) {
    // RX polls and TX commands alternate when both are due: neither starves the other.
    last_rx_poll_us_ = now;
    start_job(kJobRx, kSdepCmdUartRx, 0);
  } else if (connected_ && tx_count_ > 0 && !start_tx(false) &&
             static_cast<uint32_t>(now - last_fifo_poll_us_) >= STIPI_BLE_FIFO_POLL_US) {
    // Short of room as far as we know: ask the module (AT+BLEUARTFIFO=TX) rather than let a
    // UART TX wait 200 ms for room and fail; the frames wait in the ring meanwhile.
    last_fifo_poll_us_ = now;
    job_text_ = kAtFifoTx;
    start_job(kJobFifo, kSdepCmdAtWrapper, sizeof(kAtFifoTx) - 1);
  }
}

void BleUartLink::start_job(Job job, uint16_t id, uint16_t len) {
  job_ = job;
  job_id_ = id;
  job_len_ = len;
  job_sent_ = 0;
  awaiting_ = false;
  failed_ = false;
  reply_len_ = 0;
  job_start_us_ = clock_.micros();
  busy_mark_ = sdep_.not_ready_seen();
}

// One UART TX command carries whole frames only (up to the last 0x00 in the first
// STIPI_BLE_TX_CHUNK bytes, and, with flow control, in the FIFO room the module reported), so
// the module never truncates one and a refused command loses whole frames: seq gaps.
bool BleUartLink::start_tx(bool dry_run) {
  uint16_t limit = tx_count_ < STIPI_BLE_TX_CHUNK ? tx_count_ : STIPI_BLE_TX_CHUNK;
  if (fifo_supported_ && fifo_room_ < limit) limit = fifo_room_;
  uint16_t len = 0;
  for (uint16_t i = 0; i < limit; ++i) {
    if (tx_at(i) == 0) len = static_cast<uint16_t>(i + 1);
  }
  if (len == 0 || dry_run) return len != 0;
  start_job(kJobTx, kSdepCmdUartTx, len);
  return true;
}

// "<free>\r\nOK\r\n": the digits before the status line. "ERROR": a module firmware without the
// command (before 0.6.7): no flow control, as before.
void BleUartLink::on_fifo_reply(bool ok) {
  if (ok && reply_len_ >= 5 && memcmp(reply_, "ERROR", 5) == 0) {
    fifo_supported_ = false;
    return;
  }
  if (!ok || !reply_ok()) return;
  uint32_t room = 0;
  for (uint8_t i = 0; i + 6 < reply_len_; ++i) {  // the digits before "\r\nOK\r\n"
    const uint8_t c = reply_[i];
    room = (c >= '0' && c <= '9') ? room * 10 + (c - '0') : 0;
  }
  fifo_room_ = room > 0xFFFF ? 0xFFFF : static_cast<uint16_t>(room);
}

// SDEP.md "IRQ Pin": a packet waiting before our command goes out is an answer to an earlier
// one that timed out; read it (and drop it) rather than send over it. True while one was read.
bool BleUartLink::drain_stale_answer() {
  if (!spi_.irq()) return false;
  SdepPacket p;
  const SdepStatus st = sdep_.read_packet(p);
  if (st == kSdepAgain) return false;  // IRQ's lag after the last packet (0xFF): nothing there
  if (p.type != kSdepAlert) ++stale_answers_;
  return true;
}

void BleUartLink::step() {
  const uint32_t now = clock_.micros();
  if (awaiting_) {
    step_receive(now);
  } else {
    step_send(now);
  }
  if (job_ != kJobNone && static_cast<uint32_t>(now - job_start_us_) >= STIPI_SDEP_TIMEOUT_US) {
    // No module, a busy one, or no answer in time: bounded, and nothing waited for it. A
    // module that was up and now answers nothing (or only 0xFE) several times restarted.
    const bool was_ready = state_ == kReady;
    finish(false);
    if (was_ready && ++silent_ >= STIPI_BLE_SILENT_TO_REPROBE) module_lost();
  }
}

void BleUartLink::step_send(uint32_t) {
  if (job_sent_ == 0 && drain_stale_answer()) return;  // the command goes on a later pass
  uint8_t buf[kSdepMaxPayload];
  const uint16_t left = static_cast<uint16_t>(job_len_ - job_sent_);
  const uint8_t n = left > kSdepMaxPayload ? kSdepMaxPayload : static_cast<uint8_t>(left);
  for (uint8_t i = 0; i < n; ++i) {
    const uint16_t at = static_cast<uint16_t>(job_sent_ + i);
    buf[i] = job_ == kJobTx ? tx_at(at) : static_cast<uint8_t>(job_text_[at]);
  }
  const bool more = job_sent_ + n < job_len_;  // SDEP.md "Command Messages": More data bit
  if (sdep_.send_packet(job_id_, buf, n, more) != kSdepOk) return;  // 0xFE: next pass
  job_sent_ = static_cast<uint16_t>(job_sent_ + n);
  if (!more) awaiting_ = true;  // the one response comes after the last packet
}

void BleUartLink::step_receive(uint32_t) {
  SdepPacket p;
  const SdepStatus st = sdep_.read_packet(p);
  if (st == kSdepAgain) return;
  if (st != kSdepOk) {
    finish(false);
    return;
  }
  if (p.type == kSdepAlert) return;  // unsolicited: not our answer
  if (p.id != job_id_) {
    finish(false);
    return;
  }
  on_payload(p);
  if (!p.more) finish(true);  // SDEP.md "Response Messages": reassembled
}

void BleUartLink::on_payload(const SdepPacket& p) {
  for (uint8_t i = 0; i < p.len; ++i) {
    if (job_ == kJobRx) {
      if (rx_count_ < STIPI_BLE_RX_FIFO) {
        rx_[(rx_head_ + rx_count_) % STIPI_BLE_RX_FIFO] = p.payload[i];
        ++rx_count_;
      }
    } else if (reply_len_ < sizeof(reply_)) {
      reply_[reply_len_++] = p.payload[i];
    } else {  // keep the last bytes: the status line ends the reply
      memmove(reply_, reply_ + 1, sizeof(reply_) - 1);
      reply_[sizeof(reply_) - 1] = p.payload[i];
    }
  }
}

bool BleUartLink::reply_ok() const {
  return reply_len_ >= 4 && memcmp(reply_ + reply_len_ - 4, "OK\r\n", 4) == 0;
}

void BleUartLink::drop_tx(uint16_t bytes) {
  tx_head_ = static_cast<uint16_t>((tx_head_ + bytes) % STIPI_BLE_TX_RING);
  tx_count_ = static_cast<uint16_t>(tx_count_ - bytes);
}

// An "ATE=0" probe failed. 0xFE answers mean the module is there and still booting (SDEP.md,
// "SDEP Packet and SPI Error Identifier"): keep probing, up to STIPI_BLE_BOOT_MAX_US. Nothing
// at all, STIPI_BLE_PROBE_ATTEMPTS times: absent until the back-off ends.
void BleUartLink::probe_failed(uint32_t now, bool busy) {
  const bool booting_too_long = static_cast<uint32_t>(now - since_us_) >= STIPI_BLE_BOOT_MAX_US;
  if ((busy && !booting_too_long) || ++attempts_ < STIPI_BLE_PROBE_ATTEMPTS) return;
  state_ = kAbsent;  // no SPI traffic until the back-off ends
  since_us_ = now;
}

// A module that was up restarted (its echo is back) or stopped answering: what was queued for
// its central is lost (counted), and it is probed again as after a reset.
void BleUartLink::module_lost() {
  ++module_resets_;
  for (uint16_t i = 0; i < tx_count_; ++i) frames_lost_ += tx_at(i) == 0;
  drop_tx(tx_count_);
  connected_ = false;
  fifo_room_ = 0;
  fifo_supported_ = true;  // a restarted module may have other firmware: ask again
  job_ = kJobNone;
  start_boot(static_cast<uint32_t>(clock_.micros() - STIPI_BLE_BOOT_US));  // probe at once
  state_ = kProbing;
}

void BleUartLink::finish(bool ok) {
  const Job job = job_;
  job_ = kJobNone;
  last_job_ = job;
  if (ok) silent_ = 0;
  if (job == kJobEcho) {
    if (ok && reply_ok()) {
      state_ = kReady;
      backoff_us_ = STIPI_BLE_RETRY_MIN_US;
      last_conn_poll_us_ = static_cast<uint32_t>(clock_.micros() - STIPI_BLE_CONN_POLL_US);
    } else {
      probe_failed(clock_.micros(), sdep_.not_ready_seen() != busy_mark_);
    }
  } else if (job == kJobConn) {
    // "0\r\nOK\r\n" / "1\r\nOK\r\n" (7 bytes). Longer: the command was echoed, so echo is on
    // again, which only a restart of the module does: probe it again (ATE=0).
    if (ok && reply_ok() && reply_len_ > 7) {
      module_lost();
      return;
    }
    const bool now_conn = ok && reply_ok() && reply_len_ >= 7 && reply_[reply_len_ - 7] == '1';
    if (now_conn && !connected_) fifo_room_ = 0;  // a new central: ask for the room first
    if (now_conn && !connected_ && tx_count_ < STIPI_BLE_TX_RING) {
      tx_[(tx_head_ + tx_count_) % STIPI_BLE_TX_RING] = 0;  // new central: frame boundary
      ++tx_count_;
    }
    if (!now_conn && connected_) {
      for (uint16_t i = 0; i < tx_count_; ++i) frames_lost_ += tx_at(i) == 0;
      drop_tx(tx_count_);
    }
    connected_ = now_conn;
  } else if (job == kJobTx) {
    // An answer without "ERROR" means the module took the bytes; ERROR (FIFO still full after
    // ~200 ms, hardware.md), an error packet or no answer: the frames in it are lost.
    const bool refused = !ok || (reply_len_ >= 5 && memcmp(reply_, "ERROR", 5) == 0);
    if (refused) {
      ++tx_failures_;
      for (uint16_t i = 0; i < job_len_; ++i) frames_lost_ += tx_at(i) == 0;
      fifo_room_ = 0;  // ask again before the next one
    } else {
      fifo_room_ = fifo_room_ > job_len_ ? static_cast<uint16_t>(fifo_room_ - job_len_) : 0;
    }
    drop_tx(job_len_);
  } else if (job == kJobFifo) {
    on_fifo_reply(ok);
  }
}

int16_t BleUartLink::read() {
  if (rx_count_ == 0) return -1;
  const uint8_t b = rx_[rx_head_];
  rx_head_ = static_cast<uint8_t>((rx_head_ + 1) % STIPI_BLE_RX_FIFO);
  --rx_count_;
  return b;
}

bool BleUartLink::write_frame(const uint8_t* data, uint8_t len) {
  if (!is_open() || len == 0 || data[len - 1] != 0) return false;
  if (len > STIPI_BLE_TX_RING - tx_count_) return false;  // no room: a counted seq gap
  for (uint8_t i = 0; i < len; ++i) {
    tx_[(tx_head_ + tx_count_) % STIPI_BLE_TX_RING] = data[i];
    ++tx_count_;
  }
  return true;
}

}  // namespace stipi
