# ruff: noqa: E501  (A2ML lines as a supplier writes them)
"""A test A2L as an ECU supplier might ship it: an ASAM-like XCP A2ML, MOD_PAR with a paged CalData segment,
IF_DATA XCP on CAN, standard COMPU_METHODs and RECORD_LAYOUTs, and the given body (outside review 2026-11-29)."""

AML = r"""
    /begin A2ML
      struct Protocol_Layer {
        uint; uint; uint; uint; uint; uint; uint; uint;
        uchar; uint;
        enum { "BYTE_ORDER_MSB_LAST" = 0, "BYTE_ORDER_MSB_FIRST" = 1 };
        enum { "ADDRESS_GRANULARITY_BYTE" = 1, "ADDRESS_GRANULARITY_WORD" = 2, "ADDRESS_GRANULARITY_DWORD" = 4 };
        taggedstruct {
          ("OPTIONAL_CMD" enum { "GET_COMM_MODE_INFO" = 0xFB, "GET_SEED" = 0xF8, "UNLOCK" = 0xF7, "SHORT_UPLOAD" = 0xF4,
            "BUILD_CHECKSUM" = 0xF3, "DOWNLOAD_NEXT" = 0xEF, "SET_CAL_PAGE" = 0xEB, "GET_CAL_PAGE" = 0xEA })*;
        };
      };
      struct Page { uchar;
        enum { "ECU_ACCESS_NOT_ALLOWED" = 0, "ECU_ACCESS_WITHOUT_XCP_ONLY" = 1, "ECU_ACCESS_WITH_XCP_ONLY" = 2, "ECU_ACCESS_DONT_CARE" = 3 };
        enum { "XCP_READ_ACCESS_NOT_ALLOWED" = 0, "XCP_READ_ACCESS_WITHOUT_ECU_ONLY" = 1, "XCP_READ_ACCESS_WITH_ECU_ONLY" = 2, "XCP_READ_ACCESS_DONT_CARE" = 3 };
        enum { "XCP_WRITE_ACCESS_NOT_ALLOWED" = 0, "XCP_WRITE_ACCESS_WITHOUT_ECU_ONLY" = 1, "XCP_WRITE_ACCESS_WITH_ECU_ONLY" = 2, "XCP_WRITE_ACCESS_DONT_CARE" = 3 };
        taggedstruct { "INIT_SEGMENT" uchar; };
      };
      struct Segment { uchar; uchar; uchar; uchar; uchar;
        taggedstruct { (block "PAGE" struct Page)*; (block "CHECKSUM" struct { enum { "XCP_ADD_44" = 4, "XCP_CRC_32" = 9 }; })*; };
      };
      struct CAN_Parameters { uint;
        taggedstruct { "CAN_ID_BROADCAST" ulong; "CAN_ID_MASTER" ulong; "CAN_ID_MASTER_INCREMENTAL"; "CAN_ID_SLAVE" ulong;
          "BAUDRATE" ulong; "SAMPLE_POINT" uchar; "MAX_DLC_REQUIRED";
          (block "DAQ_LIST_CAN_ID" struct { uint; taggedstruct { "VARIABLE"; "FIXED" ulong; }; })*; };
      };
      taggedstruct Common_Parameters { block "PROTOCOL_LAYER" struct Protocol_Layer; block "SEGMENT" struct Segment; };
      block "IF_DATA" taggedunion if_data {
        "XCP" struct { taggedstruct Common_Parameters;
          taggedstruct { (block "XCP_ON_CAN" struct { struct CAN_Parameters; taggedstruct Common_Parameters; })*; };
        };
      };
    /end A2ML
"""
IFDATA_DEFAULT = """
    /begin IF_DATA XCP
      /begin PROTOCOL_LAYER 0x0101 25 25 25 25 25 25 25 8 8 BYTE_ORDER_MSB_LAST ADDRESS_GRANULARITY_BYTE
        OPTIONAL_CMD BUILD_CHECKSUM OPTIONAL_CMD SET_CAL_PAGE OPTIONAL_CMD GET_CAL_PAGE
      /end PROTOCOL_LAYER
      /begin XCP_ON_CAN 0x0100 CAN_ID_MASTER 0x7E0 CAN_ID_SLAVE 0x7E1 BAUDRATE 500000 /end XCP_ON_CAN
    /end IF_DATA
"""
MODPAR = """
    /begin MOD_PAR ""
      /begin MEMORY_SEGMENT CalData "cal" DATA FLASH INTERN 0x40000000 0x1000 -1 -1 -1 -1 -1
        /begin IF_DATA XCP
          /begin SEGMENT 0 2 0 0 0
            /begin CHECKSUM XCP_CRC_32 /end CHECKSUM
            /begin PAGE 0 ECU_ACCESS_DONT_CARE XCP_READ_ACCESS_DONT_CARE XCP_WRITE_ACCESS_NOT_ALLOWED /end PAGE
            /begin PAGE 1 ECU_ACCESS_DONT_CARE XCP_READ_ACCESS_DONT_CARE XCP_WRITE_ACCESS_DONT_CARE /end PAGE
          /end SEGMENT
        /end IF_DATA
      /end MEMORY_SEGMENT
    /end MOD_PAR
"""
STD = """
    /begin COMPU_METHOD CM_ID "" IDENTICAL "%6.2" "" /end COMPU_METHOD
    /begin COMPU_METHOD CM_LIN "" LINEAR "%8.3" "Nm" COEFFS_LINEAR 0.01 -10.0 /end COMPU_METHOD
    /begin COMPU_METHOD CM_RAT "" RAT_FUNC "%8.4" "-" COEFFS 0 100 0 0 0 1 /end COMPU_METHOD
    /begin RECORD_LAYOUT RL_UBYTE FNC_VALUES 1 UBYTE ROW_DIR DIRECT /end RECORD_LAYOUT
    /begin RECORD_LAYOUT RL_SBYTE FNC_VALUES 1 SBYTE ROW_DIR DIRECT /end RECORD_LAYOUT
    /begin RECORD_LAYOUT RL_UWORD FNC_VALUES 1 UWORD ROW_DIR DIRECT /end RECORD_LAYOUT
    /begin RECORD_LAYOUT RL_SWORD FNC_VALUES 1 SWORD ROW_DIR DIRECT /end RECORD_LAYOUT
    /begin RECORD_LAYOUT RL_ULONG FNC_VALUES 1 ULONG ROW_DIR DIRECT /end RECORD_LAYOUT
    /begin RECORD_LAYOUT RL_SLONG FNC_VALUES 1 SLONG ROW_DIR DIRECT /end RECORD_LAYOUT
    /begin RECORD_LAYOUT RL_U64 FNC_VALUES 1 A_UINT64 ROW_DIR DIRECT /end RECORD_LAYOUT
    /begin RECORD_LAYOUT RL_F32 FNC_VALUES 1 FLOAT32_IEEE ROW_DIR DIRECT /end RECORD_LAYOUT
    /begin RECORD_LAYOUT RL_F64 FNC_VALUES 1 FLOAT64_IEEE ROW_DIR DIRECT /end RECORD_LAYOUT
"""


def a2l(
    body: str,
    modcommon: str = "BYTE_ORDER MSB_LAST",
    ifdata: str = IFDATA_DEFAULT,
    std: str = STD,
    aml: str = AML,
    modpar: str = MODPAR,
) -> str:
    return f"""ASAP2_VERSION 1 71
/begin PROJECT P ""
  /begin MODULE ECU ""
{aml}
    /begin MOD_COMMON "" {modcommon} /end MOD_COMMON
{modpar}
{ifdata}
{std}
{body}
  /end MODULE
/end PROJECT
"""
