// tx_queue.h -- a byte ring that takes whole wire frames and gives them out in pieces.
//
// Owns: the bytes of frames accepted for a link whose transmit buffer has less room than a
// frame (USB CDC: the endpoint bank). A frame goes in whole or not at all; the glue drains the
// ring with as many bytes as the hardware takes now, so a frame that does not fit the space
// left is split across passes, never dropped or truncated.
#ifndef STIPI_CORE_TX_QUEUE_H
#define STIPI_CORE_TX_QUEUE_H

#include <stdint.h>

namespace stipi {

template <uint16_t N>
class TxQueue {
 public:
  TxQueue() : head_(0), count_(0) {}
  // The whole frame, or nothing (false) when it does not fit.
  bool push(const uint8_t* data, uint8_t len) {
    if (len > N - count_) return false;
    for (uint8_t i = 0; i < len; ++i) buf_[(head_ + count_ + i) % N] = data[i];
    count_ = static_cast<uint16_t>(count_ + len);
    return true;
  }
  uint16_t count() const { return count_; }
  // Contiguous queued bytes from the oldest (up to the wrap); *n gets their number.
  const uint8_t* front(uint16_t* n) const {
    *n = static_cast<uint16_t>(head_ + count_ <= N ? count_ : N - head_);
    return buf_ + head_;
  }
  void pop(uint16_t n) {
    if (n > count_) n = count_;
    head_ = static_cast<uint16_t>((head_ + n) % N);
    count_ = static_cast<uint16_t>(count_ - n);
  }
  // Hand queued bytes to `write(ctx, data, max)` (returns bytes taken) until it takes none.
  template <typename Writer>
  void drain(Writer& write) {
    while (count_ > 0) {
      uint16_t n = 0;
      const uint8_t* p = front(&n);
      const uint16_t took = write(p, n);
      if (took == 0) return;
      pop(took);
    }
  }

 private:
  uint8_t buf_[N];
  uint16_t head_;
  uint16_t count_;
};

}  // namespace stipi

#endif
