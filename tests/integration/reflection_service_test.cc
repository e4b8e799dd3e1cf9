// Server reflection with source info: starts an in-process server with the
// BehaviorSystem service (no overrides), the default health service and our
// reflection services, and queries both grpc.reflection.v1alpha and
// grpc.reflection.v1 like grpcurl does.

#include "behaviorlib/reflection/reflection_service.h"

#include <gmock/gmock.h>
#include <google/protobuf/descriptor.h>
#include <google/protobuf/descriptor.pb.h>
#include <google/protobuf/descriptor_database.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <memory>
#include <set>
#include <string>
#include <vector>

#include "behaviorlib/v1/behavior.grpc.pb.h"
#include "grpc/reflection/v1/reflection.grpc.pb.h"
#include "grpc/reflection/v1alpha/reflection.grpc.pb.h"

namespace {

namespace pb = google::protobuf;
using ::testing::Contains;
using ::testing::HasSubstr;
using ::testing::IsSupersetOf;

struct V1Alpha {
  using Service = grpc::reflection::v1alpha::ServerReflection;
  using Request = grpc::reflection::v1alpha::ServerReflectionRequest;
  using Response = grpc::reflection::v1alpha::ServerReflectionResponse;
};

struct V1 {
  using Service = grpc::reflection::v1::ServerReflection;
  using Request = grpc::reflection::v1::ServerReflectionRequest;
  using Response = grpc::reflection::v1::ServerReflectionResponse;
};

constexpr int kNotFound = static_cast<int>(grpc::StatusCode::NOT_FOUND);

// Leading comments of the element at `path` in `file`, or "".
std::string leadingComments(const pb::FileDescriptorProto& file, const std::vector<int>& path) {
  for (const auto& location : file.source_code_info().location()) {
    if (std::vector<int>(location.path().begin(), location.path().end()) == path) {
      return location.leading_comments();
    }
  }
  return "";
}

template <typename Version>
class ReflectionServiceTest : public ::testing::Test {
 protected:
  using Request = typename Version::Request;
  using Response = typename Version::Response;

  void SetUp() override {
    grpc::EnableDefaultHealthCheckService(true);
    reflection_ = behaviorlib::makeReflectionServices(
        {"behaviorlib.v1.BehaviorSystem", "grpc.health.v1.Health"});
    grpc::ServerBuilder builder;
    int port = 0;
    builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(), &port);
    builder.RegisterService(&behavior_system_);
    for (auto& service : reflection_) builder.RegisterService(service.get());
    server_ = builder.BuildAndStart();
    ASSERT_NE(server_, nullptr);
    ASSERT_NE(port, 0);
    stub_ = Version::Service::NewStub(grpc::CreateChannel("127.0.0.1:" + std::to_string(port),
                                                          grpc::InsecureChannelCredentials()));
  }

  void TearDown() override {
    if (server_) server_->Shutdown();
  }

  // Sends every request on one stream and returns the responses.
  std::vector<Response> exchange(const std::vector<Request>& requests) {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
    auto stream = stub_->ServerReflectionInfo(&context);
    std::vector<Response> responses;
    for (const auto& request : requests) {
      EXPECT_TRUE(stream->Write(request));
      Response response;
      if (!stream->Read(&response)) break;
      responses.push_back(std::move(response));
    }
    stream->WritesDone();
    Response extra;
    EXPECT_FALSE(stream->Read(&extra));
    const grpc::Status status = stream->Finish();
    EXPECT_TRUE(status.ok()) << status.error_message();
    EXPECT_EQ(responses.size(), requests.size());
    return responses;
  }

  Response ask(const Request& request) {
    auto responses = exchange({request});
    return responses.empty() ? Response() : responses.front();
  }

  static Request symbolRequest(const std::string& symbol) {
    Request request;
    request.set_file_containing_symbol(symbol);
    return request;
  }

  static std::vector<pb::FileDescriptorProto> files(const Response& response) {
    std::vector<pb::FileDescriptorProto> out;
    for (const auto& bytes : response.file_descriptor_response().file_descriptor_proto()) {
      pb::FileDescriptorProto file;
      EXPECT_TRUE(file.ParseFromString(bytes));
      out.push_back(std::move(file));
    }
    return out;
  }

  static std::vector<std::string> fileNames(const Response& response) {
    std::vector<std::string> names;
    for (const auto& file : files(response)) names.push_back(file.name());
    return names;
  }

  // Name of the first (requested) file, or "" with a failure.
  std::string fileOf(const std::string& symbol) {
    const Response response = ask(symbolRequest(symbol));
    EXPECT_TRUE(response.has_file_descriptor_response())
        << symbol << ": " << response.error_response().error_message();
    auto names = fileNames(response);
    return names.empty() ? "" : names.front();
  }

  behaviorlib::v1::BehaviorSystem::Service behavior_system_;
  std::vector<std::unique_ptr<grpc::Service>> reflection_;
  std::unique_ptr<grpc::Server> server_;
  std::unique_ptr<typename Version::Service::Stub> stub_;
};

using Versions = ::testing::Types<V1Alpha, V1>;
TYPED_TEST_SUITE(ReflectionServiceTest, Versions);

TYPED_TEST(ReflectionServiceTest, ListServicesNamesEveryService) {
  typename TestFixture::Request request;
  request.set_list_services("*");
  const auto response = this->ask(request);
  ASSERT_TRUE(response.has_list_services_response());
  std::vector<std::string> names;
  for (const auto& service : response.list_services_response().service()) {
    names.push_back(service.name());
  }
  EXPECT_THAT(names, IsSupersetOf({"behaviorlib.v1.BehaviorSystem", "grpc.health.v1.Health",
                                   "grpc.reflection.v1alpha.ServerReflection",
                                   "grpc.reflection.v1.ServerReflection"}));
  EXPECT_EQ(std::set<std::string>(names.begin(), names.end()).size(), names.size());
}

TYPED_TEST(ReflectionServiceTest, ServiceFileHasCommentsAndDependencies) {
  const auto response = this->ask(this->symbolRequest("behaviorlib.v1.BehaviorSystem"));
  ASSERT_TRUE(response.has_file_descriptor_response()) << response.error_response().error_message();
  const auto files = this->files(response);
  ASSERT_FALSE(files.empty());
  const auto& file = files.front();
  EXPECT_EQ(file.name(), "behaviorlib/v1/behavior.proto");
  ASSERT_TRUE(file.has_source_code_info());
  int service_index = -1;
  for (int i = 0; i < file.service_size(); ++i) {
    if (file.service(i).name() == "BehaviorSystem") service_index = i;
  }
  ASSERT_GE(service_index, 0);
  // FileDescriptorProto.service is field 6.
  EXPECT_THAT(leadingComments(file, {6, service_index}),
              HasSubstr("Served by every behavior-system process"));

  const auto names = this->fileNames(response);
  EXPECT_THAT(names,
              IsSupersetOf({"behaviorlib/v1/options.proto", "google/protobuf/struct.proto",
                            "google/protobuf/duration.proto", "google/protobuf/timestamp.proto",
                            "google/protobuf/descriptor.proto"}));
  EXPECT_EQ(std::set<std::string>(names.begin(), names.end()).size(), names.size());

  // The files are a closed set that builds a pool, keeping the comments.
  pb::SimpleDescriptorDatabase db;
  for (const auto& f : files) ASSERT_TRUE(db.Add(f)) << f.name();
  pb::DescriptorPool pool(&db);
  const auto* method = pool.FindMethodByName("behaviorlib.v1.BehaviorSystem.ListBehaviors");
  ASSERT_NE(method, nullptr);
  pb::SourceLocation location;
  ASSERT_TRUE(method->GetSourceLocation(&location));
  EXPECT_THAT(location.leading_comments, HasSubstr("Describes every hosted behavior"));
}

TYPED_TEST(ReflectionServiceTest, FindsNestedAndNonServiceSymbols) {
  const std::string behavior = "behaviorlib/v1/behavior.proto";
  EXPECT_EQ(this->fileOf("behaviorlib.v1.BehaviorSystem.ListBehaviors"), behavior);
  EXPECT_EQ(this->fileOf("behaviorlib.v1.ListBehaviorsResponse"), behavior);
  EXPECT_EQ(this->fileOf("behaviorlib.v1.ListBehaviorsResponse.robot_id"), behavior);
  EXPECT_EQ(this->fileOf("behaviorlib.v1.WatchEventsResponse.kind"), behavior);
  EXPECT_EQ(this->fileOf("behaviorlib.v1.BehaviorState"), behavior);
  EXPECT_EQ(this->fileOf("behaviorlib.v1.BEHAVIOR_STATE_INACTIVE"), behavior);
  EXPECT_EQ(this->fileOf("behaviorlib.v1.param"), "behaviorlib/v1/options.proto");
  // Declared in one file, its service generated into another (decision 21).
  EXPECT_EQ(this->fileOf("behaviorlib.v1.WaitParameters"),
            "behaviorlib/v1/behaviors/basic_quadrotor_behaviors.proto");
  EXPECT_EQ(this->fileOf("behaviorlib.v1.Wait"),
            "behaviorlib/v1/behaviors/basic_quadrotor_behaviors_services.proto");
  EXPECT_EQ(this->fileOf("google.protobuf.FieldDescriptorProto.Type"),
            "google/protobuf/descriptor.proto");
  EXPECT_EQ(this->fileOf("google.protobuf.DescriptorProto.ExtensionRange"),
            "google/protobuf/descriptor.proto");
  EXPECT_EQ(this->fileOf("grpc.health.v1.HealthCheckResponse.ServingStatus"),
            "grpc/health/v1/health.proto");
}

TYPED_TEST(ReflectionServiceTest, UnknownSymbolIsNotFound) {
  for (const std::string symbol :
       {"behaviorlib.v1.NoSuchThing", "behaviorlib.v1.BehaviorSystem.NoSuchMethod", "nope", ""}) {
    const auto response = this->ask(this->symbolRequest(symbol));
    ASSERT_TRUE(response.has_error_response()) << symbol;
    EXPECT_EQ(response.error_response().error_code(), kNotFound) << symbol;
    EXPECT_THAT(response.error_response().error_message(), HasSubstr("not found")) << symbol;
    EXPECT_THAT(response.error_response().error_message(), HasSubstr(symbol));
  }
}

TYPED_TEST(ReflectionServiceTest, StreamContinuesAfterAnError) {
  typename TestFixture::Request list;
  list.set_list_services("");
  const auto responses =
      this->exchange({this->symbolRequest("behaviorlib.v1.Nope"),
                      this->symbolRequest("behaviorlib.v1.BehaviorSystem"), list});
  ASSERT_EQ(responses.size(), 3u);
  EXPECT_TRUE(responses[0].has_error_response());
  EXPECT_TRUE(responses[1].has_file_descriptor_response());
  EXPECT_TRUE(responses[2].has_list_services_response());
}

TYPED_TEST(ReflectionServiceTest, HealthServiceIsDescribedWithComments) {
  const auto response = this->ask(this->symbolRequest("grpc.health.v1.Health"));
  ASSERT_TRUE(response.has_file_descriptor_response()) << response.error_response().error_message();
  const auto files = this->files(response);
  ASSERT_EQ(files.size(), 1u);
  EXPECT_EQ(files[0].name(), "grpc/health/v1/health.proto");
  ASSERT_EQ(files[0].service_size(), 1);
  // FileDescriptorProto.service[0].method[0] is Health.Check.
  EXPECT_THAT(leadingComments(files[0], {6, 0, 2, 0}), HasSubstr("NOT_FOUND"));
}

TYPED_TEST(ReflectionServiceTest, ReflectionServicesDescribeThemselves) {
  for (const std::string package : {"grpc.reflection.v1alpha", "grpc.reflection.v1"}) {
    const auto response = this->ask(this->symbolRequest(package + ".ServerReflection"));
    ASSERT_TRUE(response.has_file_descriptor_response()) << package;
    const auto files = this->files(response);
    ASSERT_FALSE(files.empty());
    EXPECT_EQ(files[0].package(), package);
    EXPECT_TRUE(files[0].has_source_code_info()) << package;
  }
}

// Every error carries google.rpc details: reflection describes them, with
// their comments, so grpcurl can print them.
TYPED_TEST(ReflectionServiceTest, ErrorDetailsAreDescribedWithComments) {
  const auto response = this->ask(this->symbolRequest("google.rpc.ErrorInfo"));
  ASSERT_TRUE(response.has_file_descriptor_response()) << response.error_response().error_message();
  const auto files = this->files(response);
  ASSERT_FALSE(files.empty());
  EXPECT_EQ(files[0].name(), "google/rpc/error_details.proto");
  EXPECT_TRUE(files[0].has_source_code_info());
  EXPECT_EQ(this->fileOf("google.rpc.Status"), "google/rpc/status.proto");
  EXPECT_EQ(this->fileOf("behaviorlib.v1.ErrorReason"), "behaviorlib/v1/errors.proto");
}

TYPED_TEST(ReflectionServiceTest, FallsBackToTheGeneratedPool) {
  // empty.proto is in no embedded set, but libprotobuf registers it.
  EXPECT_EQ(this->fileOf("google.protobuf.Empty"), "google/protobuf/empty.proto");
}

TYPED_TEST(ReflectionServiceTest, FileByFilename) {
  typename TestFixture::Request request;
  request.set_file_by_filename("behaviorlib/v1/options.proto");
  auto response = this->ask(request);
  ASSERT_TRUE(response.has_file_descriptor_response());
  EXPECT_THAT(
      this->fileNames(response),
      ::testing::ElementsAre("behaviorlib/v1/options.proto", "google/protobuf/descriptor.proto"));
  EXPECT_TRUE(this->files(response).front().has_source_code_info());

  request.set_file_by_filename("behaviorlib/v1/nope.proto");
  response = this->ask(request);
  ASSERT_TRUE(response.has_error_response());
  EXPECT_EQ(response.error_response().error_code(), kNotFound);
}

TYPED_TEST(ReflectionServiceTest, Extensions) {
  typename TestFixture::Request request;
  request.mutable_file_containing_extension()->set_containing_type("google.protobuf.FieldOptions");
  request.mutable_file_containing_extension()->set_extension_number(51234);
  auto response = this->ask(request);
  ASSERT_TRUE(response.has_file_descriptor_response()) << response.error_response().error_message();
  EXPECT_EQ(this->fileNames(response).front(), "behaviorlib/v1/options.proto");

  request.mutable_file_containing_extension()->set_extension_number(9999);
  response = this->ask(request);
  ASSERT_TRUE(response.has_error_response());
  EXPECT_EQ(response.error_response().error_code(), kNotFound);

  request.mutable_file_containing_extension()->set_containing_type("no.Such");
  response = this->ask(request);
  ASSERT_TRUE(response.has_error_response());
  EXPECT_EQ(response.error_response().error_code(), kNotFound);

  request.set_all_extension_numbers_of_type("google.protobuf.FieldOptions");
  response = this->ask(request);
  ASSERT_TRUE(response.has_all_extension_numbers_response());
  EXPECT_EQ(response.all_extension_numbers_response().base_type_name(),
            "google.protobuf.FieldOptions");
  EXPECT_THAT(response.all_extension_numbers_response().extension_number(), Contains(51234));

  request.set_all_extension_numbers_of_type("google.protobuf.ServiceOptions");
  response = this->ask(request);
  ASSERT_TRUE(response.has_all_extension_numbers_response());
  EXPECT_THAT(response.all_extension_numbers_response().extension_number(), Contains(51235));

  request.set_all_extension_numbers_of_type("no.Such");
  response = this->ask(request);
  ASSERT_TRUE(response.has_error_response());
  EXPECT_EQ(response.error_response().error_code(), kNotFound);
}

TYPED_TEST(ReflectionServiceTest, EchoesHostAndOriginalRequest) {
  auto request = this->symbolRequest("behaviorlib.v1.BehaviorSystem");
  request.set_host("robot-1:50051");
  const auto response = this->ask(request);
  EXPECT_EQ(response.valid_host(), "robot-1:50051");
  EXPECT_EQ(response.original_request().SerializeAsString(), request.SerializeAsString());
}

TYPED_TEST(ReflectionServiceTest, EmptyRequestIsInvalidArgument) {
  const auto response = this->ask(typename TestFixture::Request());
  ASSERT_TRUE(response.has_error_response());
  EXPECT_EQ(response.error_response().error_code(),
            static_cast<int>(grpc::StatusCode::INVALID_ARGUMENT));
}

}  // namespace
