// sampler.cpp -- ISR -> main ring buffer with drop-until-empty overflow (see sampler.h).
#include "sampler.h"

#include "hal.h"

namespace stipi {

static_assert((STIPI_RING_CAPACITY & (STIPI_RING_CAPACITY - 1)) == 0 && STIPI_RING_CAPACITY <= 128,
              "ring capacity must be a power of two <= 128");

Sampler::Sampler()
    : head_(0), count_(0), overflow_(false), taken_(0), dropped_(0), first_index_(0),
      first_t_us_(0), period_us_(0) {}

void Sampler::set_period(uint16_t period_us) { period_us_ = period_us; }

void Sampler::isr_push(uint16_t adc, uint32_t t_us) {
  const uint32_t index = taken_;
  taken_ = index + 1;
  if (overflow_) {
    if (count_ != 0) {
      dropped_ = dropped_ + 1;
      return;
    }
    overflow_ = false;
  }
  if (count_ == kCapacity) {
    overflow_ = true;
    dropped_ = dropped_ + 1;
    return;
  }
  if (count_ == 0) {
    first_index_ = index;
    first_t_us_ = t_us;
  }
  ring_[head_] = adc;
  head_ = static_cast<uint8_t>((head_ + 1) & (kCapacity - 1));
  count_ = static_cast<uint8_t>(count_ + 1);
}

void Sampler::isr_drop() {
  taken_ = taken_ + 1;
  dropped_ = dropped_ + 1;
  if (count_ != 0) overflow_ = true;  // keep the ring contiguous
}

uint8_t Sampler::available() const {
  IrqGuard guard;
  return count_;
}

uint8_t Sampler::pop(Batch& out, uint8_t max) {
  const uint8_t cap = sizeof(out.adc) / sizeof(out.adc[0]);
  if (max > cap) max = cap;
  IrqGuard guard;
  uint8_t n = count_ < max ? count_ : max;
  out.count = n;
  out.period_us = period_us_;
  out.first_index = first_index_;
  out.t_us = first_t_us_;
  uint8_t tail = static_cast<uint8_t>((head_ - count_) & (kCapacity - 1));
  for (uint8_t i = 0; i < n; ++i) {
    out.adc[i] = ring_[tail];
    tail = static_cast<uint8_t>((tail + 1) & (kCapacity - 1));
  }
  count_ = static_cast<uint8_t>(count_ - n);
  first_index_ = first_index_ + n;
  first_t_us_ = first_t_us_ + static_cast<uint32_t>(n) * period_us_;
  return n;
}

void Sampler::clear() {
  IrqGuard guard;
  count_ = 0;
}

bool Sampler::overflowing() const {
  IrqGuard guard;
  return overflow_;
}

uint32_t Sampler::dropped() const {
  IrqGuard guard;
  return dropped_;
}

uint32_t Sampler::taken() const {
  IrqGuard guard;
  return taken_;
}

}  // namespace stipi
