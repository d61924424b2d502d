#include <gtest/gtest.h>

#include "prism/v1/session.pb.h"

namespace prism {
namespace {

TEST(ProtoTest, EnvelopeRoundTripKeepsTheBody) {
  v1::Envelope env;
  env.set_protocol_version(v1::PROTOCOL_VERSION_1);
  v1::Frame* frame = env.mutable_frame();
  frame->set_session_id("s-1");
  frame->set_sequence_number(42);
  frame->set_timestamp_ns(1'000'000'123);
  frame->set_codec(v1::FRAME_CODEC_PNG);
  const std::string bytes = env.SerializeAsString();

  v1::Envelope back;
  ASSERT_TRUE(back.ParseFromString(bytes));
  ASSERT_EQ(back.body_case(), v1::Envelope::kFrame);
  EXPECT_EQ(back.frame().sequence_number(), 42u);
  EXPECT_EQ(back.frame().timestamp_ns(), 1'000'000'123);
}

TEST(ProtoTest, GarbageDoesNotParseAsAnEnvelope) {
  v1::Envelope env;
  // A field-1 varint that never terminates is malformed.
  const std::string garbage("\x08\xff\xff\xff\xff\xff\xff\xff\xff\xff\xff\xff", 12);
  EXPECT_FALSE(env.ParseFromString(garbage));
}

}  // namespace
}  // namespace prism
