// test_tx_queue.cpp -- frames larger than the room left in the USB bank are split, not dropped.
#include <vector>

#include "../src/core/tx_queue.h"
#include "runner.h"

using namespace stipi;

namespace {
struct Bank {  // a USB endpoint that takes `room` bytes per pass
  uint16_t room = 0;
  std::vector<uint8_t> out;
  uint16_t operator()(const uint8_t* d, uint16_t n) {
    const uint16_t k = n < room ? n : room;
    out.insert(out.end(), d, d + k);
    room = static_cast<uint16_t>(room - k);
    return k;
  }
};
}  // namespace

TEST(tx_queue_splits_frames_across_passes_without_loss) {
  TxQueue<128> q;
  Bank bank;
  std::vector<uint8_t> sent;
  for (int k = 0; k < 200; ++k) {
    std::vector<uint8_t> f(static_cast<size_t>(20 + k % 57), static_cast<uint8_t>(k));
    f.back() = 0;
    if (q.push(f.data(), static_cast<uint8_t>(f.size()))) sent.insert(sent.end(), f.begin(), f.end());
    else CHECK(q.count() + f.size() > 128);  // refused only when the ring is really full
    bank.room = static_cast<uint16_t>(7 + (k * 13) % 64);  // whatever the bank has left
    q.drain(bank);
  }
  bank.room = 10000;
  q.drain(bank);
  CHECK(bank.out == sent);
  CHECK(sent.size() > 150 * 20u);
}

TEST(tx_queue_takes_whole_frames_only) {
  TxQueue<16> q;
  const uint8_t f[10] = {1, 2, 3, 4, 5, 6, 7, 8, 9, 0};
  CHECK(q.push(f, 10));
  CHECK(!q.push(f, 10));
  CHECK_EQ(q.count(), 10);
}
