// The motion parameters are one declaration in spirit: FOLLOW_PATH, ROTATE
// and HOVER are offered by the PID, MPC and platform motion systems, each
// with its own message under v1's published names, and those messages must
// stay the same field for field (name, number, type, label and the
// behaviorlib.v1.param options: ranges, defaults, units, descriptions).
// Sharing one message is a v2 change (decision 44); until then this test is
// what keeps the copies from drifting apart.

#include <google/protobuf/descriptor.h>
#include <google/protobuf/descriptor.pb.h>
#include <google/protobuf/util/message_differencer.h>
#include <gtest/gtest.h>

#include <string>
#include <vector>

#include "behaviorlib/v1/behaviors/quadrotor_motion_with_mpc_control.pb.h"
#include "behaviorlib/v1/behaviors/quadrotor_motion_with_pid_control.pb.h"
#include "behaviorlib/v1/behaviors/quadrotor_motion_with_platform_control.pb.h"

namespace behaviorlib {
namespace {

using google::protobuf::Descriptor;
using google::protobuf::FieldDescriptorProto;
using google::protobuf::util::MessageDifferencer;

// Every field of `a` and `b` as declared, in order; a difference names the
// field and shows both declarations.
void expectSameFields(const Descriptor* a, const Descriptor* b) {
  SCOPED_TRACE(a->full_name() + " against " + b->full_name());
  std::vector<std::string> names_a, names_b;
  for (int i = 0; i < a->field_count(); ++i) names_a.push_back(a->field(i)->name());
  for (int i = 0; i < b->field_count(); ++i) names_b.push_back(b->field(i)->name());
  ASSERT_EQ(names_a, names_b);
  for (int i = 0; i < a->field_count(); ++i) {
    FieldDescriptorProto fa, fb;
    a->field(i)->CopyTo(&fa);
    b->field(i)->CopyTo(&fb);
    EXPECT_TRUE(MessageDifferencer::Equals(fa, fb))
        << "field " << fa.name() << ":\n"
        << fa.DebugString() << "against\n"
        << fb.DebugString();
  }
}

TEST(MotionParameters, FollowPathIsTheSameInEverySystemThatOffersIt) {
  expectSameFields(v1::FollowPathParameters::descriptor(),
                   v1::FollowPathWithMpcControlParameters::descriptor());
}

TEST(MotionParameters, RotateIsTheSameInEverySystemThatOffersIt) {
  expectSameFields(v1::RotateWithPidControlParameters::descriptor(),
                   v1::RotateWithMpcControlParameters::descriptor());
  expectSameFields(v1::RotateWithPidControlParameters::descriptor(),
                   v1::RotateWithPlatformControlParameters::descriptor());
}

TEST(MotionParameters, HoverIsTheSameInEverySystemThatOffersIt) {
  expectSameFields(v1::KeepHoveringWithPidControlParameters::descriptor(),
                   v1::HoverWithMpcControlParameters::descriptor());
}

// The check itself can fail: two messages that differ are told apart.
TEST(MotionParameters, TheCheckTellsDifferentMessagesApart) {
  const Descriptor* follow = v1::FollowPathParameters::descriptor();
  const Descriptor* rotate = v1::RotateWithPidControlParameters::descriptor();
  std::vector<std::string> a, b;
  for (int i = 0; i < follow->field_count(); ++i) a.push_back(follow->field(i)->name());
  for (int i = 0; i < rotate->field_count(); ++i) b.push_back(rotate->field(i)->name());
  EXPECT_NE(a, b);
  // A field's declaration carries its param options (range, default, unit,
  // description), and a change in them alone is a difference.
  FieldDescriptorProto declared, changed;
  follow->field(0)->CopyTo(&declared);
  ASSERT_GT(declared.options().ByteSizeLong(), 0u) << declared.DebugString();
  changed = declared;
  changed.mutable_options()->set_deprecated(true);
  EXPECT_FALSE(MessageDifferencer::Equals(declared, changed));
}

}  // namespace
}  // namespace behaviorlib
